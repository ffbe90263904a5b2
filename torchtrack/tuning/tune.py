"""Tuning filter parameters by gradient — the Python API behind ``torchtrack tune``.

A tune config (YAML, see ``configs/tune-*.yaml`` and ``docs/tune.md``) names a filter of the
registry (``kalman``, ``imm``, ``gmphd``, ``pf``), its builder options (``model``, which hold the
start values), the ``trainable`` parameters by dotted name (everything else is frozen), the data,
the loss, the optimiser and early stopping. :func:`tune` runs it and writes

- ``params.yaml`` — the fitted parameters (``filter``, ``model``, ``params``: constrained values,
  ``raw``: unconstrained values), accepted by :func:`load_params` / :func:`load_filter`;
- ``loss.png`` — the loss curve.

Example::

    from torchtrack.tuning.tune import tune, load_filter
    report = tune("configs/tune-kalman.yaml")
    kf = load_filter(report["output"]["params"])     # the fitted KalmanFilter
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchtrack.config import read_mapping
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import write_yaml
from torchtrack.tuning.config import load_params, read_tune_config, save_params
from torchtrack.tuning.losses import sinkhorn_gospa
from torchtrack.tuning.parameters import get_values, plain, select_trainable, tunable_parameters
from torchtrack.tuning.plot import plot_loss_curve
from torchtrack.tuning.registry import Tunable, TuneData, check_keys, get_tunable, tunable_names
from torchtrack.tuning.trainer import FitResult, evaluate_loss, fit

OUTPUT_KEYS = ("dir", "params", "plot")


def load_filter(path: str | os.PathLike) -> nn.Module:
    """Build the filter a fitted-parameter file describes (``filter`` + ``model``) and load its params."""
    doc = read_mapping(path, "fitted parameters")
    if "filter" not in doc:
        raise TorchtrackError(f"{path}: missing 'filter' (one of {', '.join(tunable_names())})")
    module = get_tunable(doc["filter"], doc.get("model") or {}).build()
    load_params(module, path)
    return module


def output_dir(config: Mapping[str, Any], out: str | os.PathLike | None = None) -> Path:
    """Where a run of ``config`` writes: ``out``, else the config's ``output.dir``, else ``out/tune-FILTER``."""
    return Path(out if out is not None else (config.get("output") or {}).get("dir", f"out/tune-{config['filter']}"))


def _relative_errors(fitted: Mapping[str, Any], truth: Mapping[str, Any]) -> dict[str, Any]:
    """``max |fitted − truth| / max |truth|`` per parameter: the relative error of a scalar; for a vector
    or matrix (e.g. a transition matrix with zero entries) the largest error relative to its scale."""
    out = {}
    for n, t in truth.items():
        if n in fitted:
            f, tt = torch.as_tensor(fitted[n], dtype=torch.float64), torch.as_tensor(t, dtype=torch.float64)
            out[n] = float((f - tt).abs().max() / tt.abs().max())
    return out


def mean_scores(rows: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """The mean over ``rows`` of each number that every row has (e.g. held-out metrics over folds or draws)."""
    keys = [k for k in rows[0] if all(isinstance(r.get(k), (int, float)) for r in rows)]
    return {k: sum(float(r[k]) for r in rows) / len(rows) for k in keys}


def _score_draws(tunable: Tunable, module: nn.Module, draws: Mapping[int, list]) -> dict[str, Any]:
    """The held-out metrics on each further draw (``per_draw``, in seed order) and their means."""
    per_draw = [tunable.evaluate(module, items) for items in draws.values()]
    return {**mean_scores(per_draw), "per_draw": per_draw}


def tune(config: str | os.PathLike | Mapping[str, Any], out: str | os.PathLike | None = None,
         seed: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Run a tune config (a path or an already-read mapping); returns the report (also what the CLI
    prints and writes as JSON). ``out`` overrides ``output.dir``; ``seed`` overrides ``seed``."""
    cfg = read_tune_config(config) if not isinstance(config, Mapping) else dict(config)
    seed = int(cfg.get("seed", 0) if seed is None else seed)
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    tunable = get_tunable(cfg["filter"], cfg.get("model") or {})
    module = tunable.build()
    trainable = [cfg["trainable"]] if isinstance(cfg["trainable"], str) else list(cfg["trainable"])
    select_trainable(module, trainable)  # validates names before any data work
    loss = tunable.loss_name(cfg.get("loss"))
    output = cfg.get("output") or {}
    check_keys(output, OUTPUT_KEYS, "output")
    out_dir = output_dir(cfg, out)
    params_path = Path(output["params"]) if "params" in output and out is None else out_dir / "params.yaml"
    plot_path = Path(output["plot"]) if "plot" in output and out is None else out_dir / "loss.png"
    data = tunable.load_data(cfg["data"] or {}, generator)
    do_eval = bool(cfg.get("evaluate", True))
    batch_eval = (cfg.get("optimizer") or {}).get("batch_size") or 8

    # held-out metrics before and after (the training set stands in when nothing is held out)
    held = data.held_out or data.train

    def held_out_scores() -> dict[str, Any]:
        return {"loss": evaluate_loss(tunable, module, held, loss, batch_eval),
                **(tunable.evaluate(module, held) if do_eval else {})}

    start_derived = tunable.derived(module)
    before = tunable.evaluate(module, held) if do_eval and data.train else {}
    result = fit(tunable, module, trainable, data, loss, cfg.get("optimizer"), cfg.get("early_stopping"),
                 generator, progress)
    if data.held_out:
        before["loss"] = result.held_out[0][1]
    else:
        before["loss"] = result.train_loss[0] if result.train_loss else float("nan")
    after = held_out_scores()
    refined = None
    if cfg.get("refine"):   # a short line search on the task metric over the training items
        from torchtrack.tuning.refine import refine

        after_fit = after
        refined = refine(tunable, module, cfg["refine"], data, trainable, progress)
        after = held_out_scores()

    fitted = plain(get_values(module, trainable))
    fitted.update(tunable.derived(module))
    truth = tunable.truth(cfg["data"] or {})
    searched = refined or {"filter_evaluations": 0, "frames": 0, "seconds": 0.0}   # the line search's work
    evaluations = result.evaluations + searched["filter_evaluations"]
    report = {
        "filter": tunable.name, "trainable": trainable, "loss": loss,
        "optimizer": dict(cfg.get("optimizer") or {}), "seed": seed,
        "train_items": len(data.train), "held_out_items": len(data.held_out),
        "start": {**plain(result.start), **start_derived}, "fitted": fitted,
        "truth": truth, "relative_error": _relative_errors(fitted, truth),
        "held_out_before": before, "held_out_after": after,
        "steps": len(result.train_loss), "best_step": result.best_step, "stopped": result.stopped,
        "message": result.message, "filter_evaluations": evaluations, "frames": result.frames + searched["frames"],
        "training_passes": evaluations / max(len(data.train), 1), "seconds": result.seconds + searched["seconds"],
        "output": {"params": str(params_path), "plot": str(plot_path)},
    }
    if refined is not None:
        report["fit"] = {"values": plain(result.final), "held_out": after_fit,
                         "filter_evaluations": result.evaluations, "frames": result.frames,
                         "seconds": result.seconds}
        report["refine"] = refined
    if data.draws:
        report["held_out_draws"] = {"seeds": list(data.draws), "tuned": _score_draws(tunable, module, data.draws)}
    if cfg.get("grid"):
        from torchtrack.tuning.grid import grid_search

        grid_module = tunable.build()
        report["grid"] = grid_search(tunable, grid_module, cfg["grid"], data, progress)
        if data.draws:
            report["held_out_draws"]["grid"] = _score_draws(tunable, grid_module, data.draws)
    save_params(module, params_path, tunable.name, tunable.options)
    exported = tunable.export(module)
    if exported is not None:
        path = out_dir / exported[0]
        write_yaml(path, exported[1])
        report["output"][exported[0].split(".")[0]] = str(path)
    plot_loss_curve(result, plot_path, f"torchtrack tune {tunable.name} ({loss})")
    return report


__all__ = [
    "FitResult", "TuneData", "Tunable", "fit", "get_tunable", "get_values", "load_filter",
    "load_params", "plot_loss_curve", "save_params", "select_trainable", "sinkhorn_gospa", "tunable_names",
    "tunable_parameters", "tune",
]
