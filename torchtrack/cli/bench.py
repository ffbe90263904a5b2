"""``torchtrack bench NAME``: throughput against a reference timed in the same run."""

from torchtrack.cli import add_subcommands

NAME = "bench"
HELP = "measure throughput against a reference implementation timed in the same run"


def add_arguments(parser) -> None:
    add_subcommands(parser, "torchtrack.bench", "workload", parser.get_default("_argv_rest") or [])


def run(args) -> int:
    return args._run(args)
