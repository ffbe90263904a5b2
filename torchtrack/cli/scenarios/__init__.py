"""``torchtrack scenario NAME``: the papers' experiments, one command module each in this package (the
experiments themselves are library modules of ``torchtrack.scenarios``).

Every scenario takes ``--runs``, ``--config``, ``--plot``, ``--params``, ``--seed`` and ``--json``, with the
defaults its command module declares: ``DEFAULT_CONFIG``, ``RUNS`` and ``PARAMS`` (what a fitted-parameter file
sets; absent where ``torchtrack tune`` fits none of its filters).
"""

from torchtrack.cli import add_subcommands
from torchtrack.cli._common import add_common_options, add_scenario_options
from torchtrack.errors import TorchtrackError

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


def check_runs(runs: int) -> None:
    """``--runs`` is at least 1."""
    if runs < 1:
        raise TorchtrackError(f"--runs must be >= 1; got {runs}")
