"""Helpers shared by the command modules: common options, JSON output, tables."""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import torch

from torchtrack.config import preset_path
from torchtrack.errors import TorchtrackError


def add_common_options(parser: argparse.ArgumentParser, seed: int = 0) -> None:
    """``--seed`` and ``--json PATH``, which every command takes."""
    parser.add_argument("--seed", type=int, default=seed, help=f"random seed (default {seed})")
    parser.add_argument("--json", type=Path, default=None, metavar="PATH",
                        help="also write the reported numbers to this JSON file")


@contextmanager
def torch_threads(n: int | None):
    """Run the block with ``n`` torch intra-op threads (``None``: unchanged); restore the count after."""
    if n is not None and n < 1:
        raise TorchtrackError(f"--threads must be >= 1; got {n}")
    previous = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


PARAMS_SCENARIOS = "formation (imm), maneuver (kalman)"
"""The scenarios whose filter ``torchtrack tune`` fits (they take ``--params``), with the tune filter name."""


class _NoFittedParams(argparse.Action):
    """``--params`` of a scenario whose filter ``torchtrack tune`` cannot fit: a usage error."""

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string}: this scenario's filter is not one that torchtrack tune fits; "
                     f"fitted parameters load into: {PARAMS_SCENARIOS}")


def config_file(value: str) -> Path:
    """argparse ``type`` of every ``--config``-like option: a YAML path, or a shipped preset's name
    (``torchtrack.config.preset_path``)."""
    try:
        return preset_path(value)
    except TorchtrackError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_scenario_options(parser: argparse.ArgumentParser, default_config: Path, runs: int = 100,
                         params: str | None = None) -> None:
    """``--runs``, ``--config``, ``--plot DIR`` and ``--params FITTED.yaml``, which every ``torchtrack
    scenario`` takes; ``params`` says what a fitted-parameter file sets (None: the scenario has no tunable
    filter and ``--params`` is a usage error)."""
    parser.add_argument("--runs", type=int, default=runs, help=f"Monte Carlo runs, batched (default {runs})")
    parser.add_argument("--config", type=config_file, default=default_config,
                        help="scenario YAML or preset name (default: the preset of the scenario's name)")
    parser.add_argument("--plot", type=Path, default=None, metavar="DIR", help="write the figures here")
    if params is None:
        parser.add_argument("--params", action=_NoFittedParams, metavar="FITTED", help=argparse.SUPPRESS)
    else:
        parser.add_argument("--params", type=Path, default=None, metavar="FITTED",
                            help=f"fitted parameters from torchtrack tune (OUT/params.yaml): {params}")


def load_sections(path: Path, expected: set[str]) -> dict:
    """Read a YAML config that must consist of exactly the ``expected`` top-level sections."""
    import yaml

    if not Path(path).is_file():
        raise TorchtrackError(f"--config: no such file {path}")
    cfg = yaml.safe_load(Path(path).read_text())
    if not isinstance(cfg, dict) or set(cfg) != expected:
        raise TorchtrackError(f"{path}: expected exactly the sections {sorted(expected)}")
    return cfg


def _jsonable(obj):
    if isinstance(obj, torch.Tensor):
        return _jsonable(obj.detach().cpu().tolist())
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if hasattr(obj, "item") and not isinstance(obj, (str, bytes)):
        return obj.item()
    return obj


def write_json(path: Path | None, payload: Mapping) -> None:
    """Write ``payload`` as indented JSON when ``path`` is given (tensors become lists, NaN null)."""
    if path is None:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_jsonable(payload), indent=2) + "\n")


def format_table(header: Sequence[str], rows: Sequence[Sequence], floatfmt: str = ".3f") -> str:
    """A plain aligned text table."""
    def cell(v):
        if isinstance(v, float):
            return format(v, floatfmt)
        return str(v)

    cells = [[cell(v) for v in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(header)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(header, widths))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)
