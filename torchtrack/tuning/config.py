"""Tune configs (what to fit) and fitted-parameter files (what was fitted).

A **fitted-parameter file** is YAML::

    filter: kalman            # registry name (torchtrack.tuning.registry)
    model: {...}              # the builder options the filter was built from
    params:                   # constrained values, by dotted name — edit these by hand if you like
      measurement.sigma: 5.02
      motion.q: 0.98
    raw:                      # the unconstrained values the optimiser found (bit-exact round-trip)
      measurement.sigma: 4.995
      motion.q: 0.524

:func:`load_params` copies ``raw`` when it still maps to ``params`` (so loading reproduces the fitted
filter's output exactly) and otherwise — ``params`` edited by hand, or ``raw`` absent — sets each
parameter from its constrained value through the inverse transform.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import yaml
from torch import nn

from torchtrack.config import Checked, from_mapping, option, read_mapping
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import write_yaml
from torchtrack.tuning.parameters import get_raw, get_values, set_raw, set_values, tunable_parameters


@dataclass(frozen=True)
class OptimizerOptions(Checked):
    """The ``optimizer:`` section (:func:`torchtrack.tuning.trainer.fit`): ``name`` adam or lbfgs; ``lr``
    (default 0.05 for Adam, 1.0 for L-BFGS); ``lr_final`` (Adam: cosine decay to it over ``steps``; None:
    constant); ``steps`` (default 200 for Adam, 20 for L-BFGS); ``batch_size`` items per step (default 8 for
    Adam, all for L-BFGS); ``max_iter`` L-BFGS iterations per step; ``eval_every`` steps between held-out
    evaluations (default one epoch)."""

    name: str = option("adam", one_of=("adam", "lbfgs"))
    lr: float | None = option(None, gt=0)
    lr_final: float | None = option(None, ge=0)
    steps: int | None = option(None, ge=1)
    batch_size: int | None = option(None, ge=1)
    max_iter: int = option(10, ge=1)
    eval_every: int | None = option(None, ge=1)


@dataclass(frozen=True)
class EarlyStopping(Checked):
    """The ``early_stopping:`` section: stop after ``patience`` held-out evaluations without an improvement of
    ``min_delta``; ``restore_best``: end with the best evaluation's parameters (false: the last ones)."""

    patience: int = option(5, ge=1)
    min_delta: float = option(1e-4, ge=0)
    restore_best: bool = True


@dataclass(frozen=True)
class RefineOptions(Checked):
    """The optional ``refine:`` section (:func:`torchtrack.tuning.refine.refine`): a line search on the task
    ``metric`` (``maximize`` it, or not) over ``parameters`` (None: the trainable ones) in steps of ``step``
    (relative, see ``step_scale``), ``sweeps`` passes, within ``evaluations`` metric evaluations; ``average``
    k > 1 ends at the centroid of the k best points (one evaluation kept for it); ``lookahead``: a step that
    does not improve is followed by one twice as long."""

    metric: str = "MOTA"
    maximize: bool = True
    parameters: list | None = None
    step: float = option(0.5, gt=0)
    sweeps: int = option(2, ge=1)
    evaluations: int = option(12, ge=1)
    average: int = option(1, ge=1)
    lookahead: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.average > 1 and self.evaluations < 2:
            raise self.refuse("evaluations", f"must be >= 2 with average > 1; got {self.evaluations}")


@dataclass(frozen=True)
class TuneSections:
    """The sections of a tune config (``docs/tune.md``); each is read by the tunable filter ``filter`` names
    (:mod:`torchtrack.tuning.registry`), which checks its own keys. ``filter``, ``trainable`` and ``data`` are
    required."""

    filter: str | None = None
    model: Any = None
    trainable: Any = None
    data: Any = None
    loss: Any = None
    optimizer: OptimizerOptions = field(default_factory=OptimizerOptions)
    early_stopping: EarlyStopping = field(default_factory=EarlyStopping)
    output: Any = None
    seed: int | None = None
    evaluate: Any = None
    grid: Any = None
    refine: RefineOptions | None = None


TUNE_KEYS = tuple(f.name for f in dataclasses.fields(TuneSections))


def read_tune_config(path: str | os.PathLike, overrides: Iterable[str] = ()) -> dict:
    """A tune config with the ``KEY=VALUE`` ``overrides`` applied (:func:`apply_overrides`) and its keys and
    values checked (``filter``, ``trainable`` and ``data`` required)."""
    cfg = apply_overrides(read_mapping(path, "tune config"), overrides)
    from_mapping(TuneSections, cfg, str(path))     # unknown sections, bad types and values out of range, named
    for key in ("filter", "trainable", "data"):
        if key not in cfg:
            raise TorchtrackError(f"{path}: missing required key {key!r}")
    return cfg


def apply_overrides(cfg: dict, assignments: Iterable[str]) -> dict:
    """Set ``KEY=VALUE`` assignments in a tune config in place (``KEY`` dotted, e.g.
    ``data.held_out_frames``; ``VALUE`` read as YAML, e.g. ``[1, 128]``); returns ``cfg``. The first part
    of each key must be a tune-config key; missing mappings on the way are created."""
    for text in assignments:
        key, sep, value = text.partition("=")
        parts = key.strip().split(".")
        if not sep or not all(parts):
            raise TorchtrackError(f"--set {text!r}: expected KEY=VALUE with a dotted KEY, e.g. "
                                  f"data.held_out_frames=[1,128]")
        if parts[0] not in TUNE_KEYS:
            raise TorchtrackError(f"--set {text!r}: unknown key {parts[0]!r}; allowed: {', '.join(TUNE_KEYS)}")
        try:
            parsed = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            raise TorchtrackError(f"--set {text!r}: invalid YAML value: {getattr(exc, 'problem', exc)}") from exc
        node = cfg
        for part in parts[:-1]:
            if node.get(part) is None:
                node[part] = {}
            if not isinstance(node[part], dict):
                raise TorchtrackError(f"--set {text!r}: {part!r} is not a mapping in the config")
            node = node[part]
        node[parts[-1]] = parsed
    return cfg


def save_params(module: nn.Module, path: str | os.PathLike, filter_name: str,
                model: Mapping[str, Any] | None = None) -> Path:
    """Write the fitted-parameter file of all of ``module``'s tunable parameters (floats written with full
    precision, so reading is exact)."""
    return write_yaml(path, {"filter": filter_name, "model": dict(model or {}),
                             "params": {n: v.double().tolist() for n, v in get_values(module).items()},
                             "raw": {n: v.double().tolist() for n, v in get_raw(module).items()}})


def read_params_file(path: str | os.PathLike, filters: Iterable[str], where: str) -> dict:
    """A fitted-parameter file, checked to come from one of the tunable ``filters`` (e.g. ``("kalman",)``)
    that ``where`` (e.g. ``"scenario maneuver"``) can load."""
    doc = read_mapping(path, "fitted parameters")
    filters = tuple(filters)
    if doc.get("filter") not in filters:
        raise TorchtrackError(f"{path}: fitted parameters of a {doc.get('filter')!r} filter; {where} takes "
                              f"those of {' or '.join(map(repr, filters))} (torchtrack tune --config "
                              f"configs/tune-{filters[0]}*.yaml)")
    if not isinstance(doc.get("model") or {}, Mapping):
        raise TorchtrackError(f"{path}: 'model' must be a mapping of builder options")
    return doc


def load_params(module: nn.Module, path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Set ``module``'s parameters from a fitted-parameter file; returns the constrained values set.

    Names not in the module raise :class:`TorchtrackError` listing the valid names. The module's
    ``requires_grad`` flags are left unchanged.
    """
    doc = read_mapping(path, "fitted parameters")
    params = doc.get("params")
    if not isinstance(params, Mapping) or not params:
        raise TorchtrackError(f"{path}: needs a non-empty 'params' mapping of name: value")
    raw = doc.get("raw") or {}
    if not isinstance(raw, Mapping):
        raise TorchtrackError(f"{path}: 'raw' must be a mapping of name: value")
    valid = tunable_parameters(module)
    unknown = [n for n in params if n not in valid]
    if unknown:
        raise TorchtrackError(f"{path}: unknown parameter(s) {', '.join(map(repr, unknown))} for "
                              f"{type(module).__name__}; valid names: {', '.join(sorted(valid))}")
    for name, value in params.items():
        ref = valid[name].raw
        try:
            value_t = torch.as_tensor(value, dtype=ref.dtype, device=ref.device)
        except (TypeError, ValueError) as exc:
            raise TorchtrackError(f"{path}: params.{name} is not a number or a list of numbers") from exc
        if value_t.shape != ref.shape:
            raise TorchtrackError(f"{path}: params.{name} must have shape {tuple(ref.shape)}; got "
                                  f"{tuple(value_t.shape)}")
        if name in raw:
            set_raw(module, {name: torch.as_tensor(raw[name], dtype=ref.dtype)})
            if torch.allclose(get_values(module, [name])[name], value_t, rtol=1e-6, atol=1e-12):
                continue  # raw still maps to the written value: keep it, bit-exact
        set_values(module, {name: value_t})
    return get_values(module, list(params))
