"""``torchtrack scenario NAME``: the papers' experiments (one module each in ``torchtrack.scenarios``)."""

from torchtrack.cli import add_subcommands

NAME = "scenario"
HELP = "run one of the papers' experiments, batched over Monte Carlo runs"


def add_arguments(parser) -> None:
    add_subcommands(parser, "torchtrack.scenarios", "scenario", parser.get_default("_argv_rest") or [])


def run(args) -> int:
    return args._run(args)
