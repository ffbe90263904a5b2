"""``torchtrack scenario NAME``: the papers' experiments, one command module each in this package (the
experiments themselves are library modules of ``torchtrack.scenarios``).

Every scenario takes ``--runs``, ``--config``, ``--plot``, ``--params``, ``--seed`` and ``--json``, with the
defaults its command module declares: ``DEFAULT_CONFIG``, ``RUNS`` and ``PARAMS`` (what a fitted-parameter file
sets; absent where ``torchtrack tune`` fits none of its filters); ``PROGRESS = True`` where the scenario draws a
progress bar adds ``--no-progress``.
"""

import importlib
from collections.abc import Callable
from contextlib import nullcontext
from types import ModuleType
from typing import TypeVar

from torchtrack.cli import add_subcommands
from torchtrack.cli._common import add_common_options, add_scenario_options
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import OutputFolder, write_json

NAME = "scenario"
HELP = "run one of the papers' experiments, batched over Monte Carlo runs"
R = TypeVar("R")


def _scenario_options(parser, module) -> None:
    add_scenario_options(parser, module.DEFAULT_CONFIG, runs=module.RUNS, params=getattr(module, "PARAMS", None))
    if getattr(module, "PROGRESS", False):
        parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_common_options(parser)


def add_arguments(parser) -> None:
    add_subcommands(parser, "torchtrack.cli.scenarios", "scenario", parser.get_default("_argv_rest") or [],
                    options=_scenario_options)


def run(args) -> int:
    return args._run(args)


def run_scenario(args, name: str, scenario: ModuleType, experiment: Callable[[], R]) -> R:
    """Check ``--runs``, run ``experiment()`` (a report of the library module ``scenario``), print its
    ``format_report``, write its ``report_json`` to ``--json`` and, with ``--plot DIR``, its figures
    (``torchtrack.scenarios._NAME_plots.plot``) to ``DIR`` as one output folder, which is entered before the
    experiment, so that a folder that cannot be used is refused before any work."""
    if args.runs < 1:
        raise TorchtrackError(f"--runs must be >= 1; got {args.runs}")
    with nullcontext(None) if args.plot is None else OutputFolder(
            args.plot, f"torchtrack scenario {name}", args.force, flag="--plot", inputs=[args.config]) as plots:
        report = experiment()
        print(scenario.format_report(report))
        write_json(args.json, scenario.report_json(report))
        if plots is not None:
            paths = importlib.import_module(f"torchtrack.scenarios._{name}_plots").plot(report, plots)
    if args.plot is not None:
        print("\nplots: " + ", ".join(str(args.plot / p.name) for p in paths))
    return report
