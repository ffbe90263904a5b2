"""``torchtrack scenario NAME``: the papers' experiments, one command module each in this package (the
experiments themselves are library modules of ``torchtrack.scenarios``).

Every scenario takes ``--runs``, ``--config``, ``--plot``, ``--params``, ``--seed`` and ``--json``, with the
defaults its command module declares: ``DEFAULT_CONFIG``, ``RUNS`` and ``PARAMS`` (what a fitted-parameter file
sets; absent where ``torchtrack tune`` fits none of its filters).
"""

from contextlib import AbstractContextManager, nullcontext
from pathlib import Path

from torchtrack.cli import add_subcommands
from torchtrack.cli._common import add_common_options, add_scenario_options
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import OutputFolder

NAME = "scenario"
HELP = "run one of the papers' experiments, batched over Monte Carlo runs"


def _scenario_options(parser, module) -> None:
    add_scenario_options(parser, module.DEFAULT_CONFIG, runs=module.RUNS, params=getattr(module, "PARAMS", None))
    add_common_options(parser)


def add_arguments(parser) -> None:
    add_subcommands(parser, "torchtrack.cli.scenarios", "scenario", parser.get_default("_argv_rest") or [],
                    options=_scenario_options)


def run(args) -> int:
    return args._run(args)


def plot_folder(args, name: str) -> AbstractContextManager[Path | None]:
    """``--plot DIR`` as an output folder written as one set (``None`` without ``--plot``): entered before the
    experiment, so that a folder that cannot be used is refused before any work; the figures go to the
    staging folder it yields and appear in ``DIR`` together once the command completes."""
    if args.plot is None:
        return nullcontext(None)
    return OutputFolder(args.plot, f"torchtrack scenario {name}", args.force, flag="--plot", inputs=[args.config])


def check_runs(runs: int) -> None:
    """``--runs`` is at least 1."""
    if runs < 1:
        raise TorchtrackError(f"--runs must be >= 1; got {runs}")
