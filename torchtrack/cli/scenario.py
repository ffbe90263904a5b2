"""``torchtrack scenario NAME``: the papers' experiments (one module each in ``torchtrack.scenarios``).

Every scenario takes ``--runs``, ``--config``, ``--plot``, ``--params``, ``--seed`` and ``--json``, with the
defaults its module declares: ``DEFAULT_CONFIG``, ``RUNS`` and ``PARAMS`` (what a fitted-parameter file sets;
absent where ``torchtrack tune`` fits none of its filters).
"""

from torchtrack.cli import add_subcommands
from torchtrack.cli._common import add_common_options, add_scenario_options

NAME = "scenario"
HELP = "run one of the papers' experiments, batched over Monte Carlo runs"


def _scenario_options(parser, module) -> None:
    add_scenario_options(parser, module.DEFAULT_CONFIG, runs=module.RUNS, params=getattr(module, "PARAMS", None))
    add_common_options(parser)


def add_arguments(parser) -> None:
    add_subcommands(parser, "torchtrack.scenarios", "scenario", parser.get_default("_argv_rest") or [],
                    options=_scenario_options)


def run(args) -> int:
    return args._run(args)
