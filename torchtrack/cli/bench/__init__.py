"""``torchtrack bench NAME``: throughput against a reference timed in the same run, one command module each in
this package (the workloads and references are library modules of ``torchtrack.bench``)."""

from torchtrack.bench._timing import BenchResult
from torchtrack.cli import add_subcommands
from torchtrack.cli._common import add_common_options
from torchtrack.io.outputs import write_json

NAME = "bench"
HELP = "measure throughput against a reference implementation timed in the same run"


def add_arguments(parser) -> None:
    add_subcommands(parser, "torchtrack.cli.bench", "workload", parser.get_default("_argv_rest") or [],
                    options=lambda p, _: add_common_options(p))


def run(args) -> int:
    return args._run(args)


def report(args, result: BenchResult, text: str) -> int:
    """Print a benchmark's ``text``, write its ``payload()`` to ``--json``; the exit status 0."""
    print(text)
    write_json(args.json, result.payload())
    return 0
