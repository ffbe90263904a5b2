"""Helpers shared by the command modules: the common options, the scenarios' options and the tracker YAML."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from torchtrack.config import Bounds, preset_path
from torchtrack.errors import TorchtrackError


def add_force_option(parser: argparse.ArgumentParser, flag: str = "--out") -> None:
    """``--force`` of the commands that write an output folder, named ``flag`` in the help
    (:class:`torchtrack.io.outputs.OutputFolder`)."""
    parser.add_argument("--force", action="store_true",
                        help=f"replace {flag} even when it holds something other than this command's output")


def bounded(kind: type, **bounds) -> Callable[[str], int | float]:
    """An argparse ``type``: the text as ``kind`` (int, or a finite float) within :class:`torchtrack.config.Bounds`
    (``ge``, ``gt``, ``le``, ``lt``), otherwise a usage error (``argument --epochs: must be >= 1; got -1``)."""
    limits = Bounds(**bounds)

    def parse(text: str) -> int | float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {'a whole number' if kind is int else 'a number'}; "
                                             f"got {text!r}") from None
        if kind is float and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number; got {text!r}")
        found = limits.problem("", value)
        if found:
            raise argparse.ArgumentTypeError(found[1])
        return value

    parse.__name__ = kind.__name__
    return parse


positive_int = bounded(int, ge=1)
SEED = bounded(int, ge=0, lt=2**63)
"""A ``--seed``: a whole number that torch's and NumPy's generators both take (0 to 2⁶³ − 1)."""
nonnegative_int = bounded(int, ge=0)
positive_float = bounded(float, gt=0)
nonnegative_float = bounded(float, ge=0)
probability = bounded(float, ge=0, le=1)


def add_common_options(parser: argparse.ArgumentParser, seed: int | None = 0, random: bool = True,
                       seed_help: str = "random seed; the same seed gives the same result") -> None:
    """``--json PATH``, which every command takes, and ``--seed`` (default ``seed``) where the command draws
    random numbers (``random=False``: it draws none and takes no ``--seed``)."""
    if random:
        parser.add_argument("--seed", type=SEED, default=seed, help=seed_help)
    parser.add_argument("--json", type=Path, default=None, metavar="PATH",
                        help="also write the reported numbers to this JSON file")


PARAMS_SCENARIOS = "formation (imm), maneuver (kalman)"
"""The scenarios whose filter ``torchtrack tune`` fits (they take ``--params``), with the tune filter name."""


class _NoFittedParams(argparse.Action):
    """``--params`` of a scenario whose filter ``torchtrack tune`` cannot fit: a usage error."""

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string}: this scenario's filter is not one that torchtrack tune fits; "
                     f"fitted parameters load into: {PARAMS_SCENARIOS}")


TRACKER_PRESETS = ("gmphd", "gmphd-paper")
"""The presets that hold tracker options, one section per tracker name (``torchtrack track --config``)."""
PIPELINE_PRESETS = ("pipeline", "pipeline-online", "pipeline-fewer-switches", "select-fewer-switches")
"""The presets of the video pipeline's settings (``--pipeline-config``, ``torchtrack demo --config``)."""
VIDEO_PRESETS = ("video", "camera-soft", "camera-small-dark", "camera-harsh")
"""The presets of the synthetic video generator (``simulate-video --config``, ``eval-detector --config``)."""
TUNE_PRESETS = ("tune-gmphd-sim", "tune-gmphd-wpafb", "tune-imm-formation", "tune-kalman", "tune-kalman-wpafb")
"""The presets of ``torchtrack tune --config``."""


def config_file(*presets: str) -> Callable[[str], Path]:
    """argparse ``type`` of a ``--config``-like option: a YAML path, or the name of one of ``presets``
    (:func:`torchtrack.config.preset_path`); a wrong name is a usage error listing only those presets."""

    def parse(value: str) -> Path:
        try:
            return preset_path(value, presets)
        except TorchtrackError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parse.__name__ = "config"
    parse.presets = presets
    return parse


def add_scenario_options(parser: argparse.ArgumentParser, default_config: Path, runs: int = 100,
                         params: str | None = None) -> None:
    """``--runs``, ``--config``, ``--plot DIR`` and ``--params FITTED.yaml``, which every ``torchtrack
    scenario`` takes; ``params`` says what a fitted-parameter file sets (None: the scenario has no tunable
    filter and ``--params`` is a usage error)."""
    parser.add_argument("--runs", type=int, default=runs, help=f"Monte Carlo runs, batched (default {runs})")
    parser.add_argument("--config", type=config_file(default_config.stem), default=default_config,
                        help="scenario YAML or preset name (default: the preset of the scenario's name)")
    parser.add_argument("--plot", type=Path, default=None, metavar="DIR",
                        help="write the figures into this folder (they appear together when the run completes)")
    parser.add_argument("--force", action="store_true",
                        help="replace --plot even when it holds something other than this scenario's figures")
    if params is None:
        parser.add_argument("--params", action=_NoFittedParams, metavar="FITTED", help=argparse.SUPPRESS)
    else:
        parser.add_argument("--params", type=Path, default=None, metavar="FITTED",
                            help=f"fitted parameters from torchtrack tune (OUT/params.yaml): {params}")


def print_calibration(record: dict[str, Any]) -> None:
    """The one-line verdict of a ``--calibrate`` run (its ``calibration.json`` record), on stderr."""
    print(f"calibration: {record['status']}: {record['message']}", file=sys.stderr)
