"""K-fold cross-validation of a tune config (``torchtrack tune --folds K``).

A single held-out block judges a tuned filter on one stretch of data; on the WPAFB example the sign
of "tuned − grid" changes when the block moves by 16 frames (docs/tune.md). Cross-validation holds
out each of ``K`` contiguous blocks in turn, fits (and line-searches, and runs the grid) on the rest,
and averages the held-out metrics over the folds.

Blocks: for frame data (``data.train_frames`` / ``data.held_out_frames``, the GM-PHD) the frames from
the first to the last of those spans are cut into ``K`` contiguous blocks of near-equal length; the
training frames of fold ``k`` are the spans either side of block ``k``. For item data (``data.held_out``,
the Kalman, IMM and particle filters) the items, in the order the data section makes them, are cut the
same way (``held_out: {fold: k, folds: K}``).
"""

from __future__ import annotations

import copy
import math
import os
import statistics
from collections.abc import Mapping
from typing import Any

from torchtrack.errors import TorchtrackError
from torchtrack.tuning.registry import fold_bounds


def fold_config(config: Mapping[str, Any], fold: int, folds: int) -> dict[str, Any]:
    """A copy of the tune ``config`` holding out block ``fold`` (0-based) of ``folds`` (see the module)."""
    cfg = copy.deepcopy(dict(config))
    data = cfg.get("data") or {}
    if cfg.get("filter") == "gmphd":
        from torchtrack.tuning.gmphd import frame_span, train_spans

        if "train_frames" not in data:
            raise TorchtrackError("cross-validation of frame data needs data.train_frames (the frames to cut "
                                  "into folds, with data.held_out_frames if given)")
        spans = train_spans(data["train_frames"])
        if data.get("held_out_frames"):
            spans.append(frame_span(data["held_out_frames"], "held_out_frames"))
        first, last = min(s[0] for s in spans), max(s[1] for s in spans)
        lo, hi = fold_bounds(last - first + 1, folds)[fold]
        held = [first + lo, first + hi - 1]
        data["train_frames"] = [s for s in ([first, held[0] - 1], [held[1] + 1, last]) if s[0] <= s[1]]
        data["held_out_frames"] = held
    else:
        data["held_out"] = {"fold": fold, "folds": folds}
    cfg["data"] = data
    return cfg


def _held_out(report: Mapping[str, Any]) -> dict[str, Any]:
    """Per method, the held-out metrics (on the further draws where the config has them)."""
    draws = report.get("held_out_draws")
    out = {"tuned": dict(draws["tuned"]) if draws else dict(report["held_out_after"])}
    if "grid" in report:
        out["grid"] = dict(draws["grid"]) if draws else dict(report["grid"]["held_out"])
    for scores in out.values():
        scores.pop("per_draw", None)
    return out


def cross_validate(config: Mapping[str, Any], folds: int, out: str | os.PathLike | None = None,
                   seed: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Run :func:`torchtrack.tuning.tune.tune` once per fold (outputs under ``OUT/fold-K``) and summarise.

    Returns ``{"folds", "runs"`` (each fold's report, with its ``held_out_frames`` or items),
    ``"per_fold"`` (per method the held-out metrics of each fold: on the further draws where the config
    has ``held_out_draws``, else on the held-out items), ``"mean"`` (per method their mean over the folds)
    and, with a grid, ``"difference"`` (tuned − grid of the grid's metric per fold, its mean and standard
    error)}``."""
    from torchtrack.tuning.tune import mean_scores, output_dir, tune

    base = output_dir(config, out)
    runs, per_fold = [], []
    for k in range(folds):
        cfg = fold_config(config, k, folds)
        report = tune(cfg, out=base / f"fold-{k + 1}", seed=seed, progress=progress)
        report["fold"] = k + 1
        if "held_out_frames" in cfg["data"]:
            report["held_out_frames"] = cfg["data"]["held_out_frames"]
        runs.append(report)
        per_fold.append(_held_out(report))
    methods = list(per_fold[0])
    summary: dict[str, Any] = {
        "folds": folds, "runs": runs,
        "per_fold": {m: [f[m] for f in per_fold] for m in methods},
        "mean": {m: mean_scores([f[m] for f in per_fold]) for m in methods},
    }
    if "grid" in methods:
        metric = runs[0]["grid"]["metric"]
        diffs = [f["tuned"][metric] - f["grid"][metric] for f in per_fold]
        summary["difference"] = {"metric": metric, "per_fold": diffs, "mean": statistics.fmean(diffs),
                                 "stderr": statistics.stdev(diffs) / math.sqrt(folds)}
    return summary
