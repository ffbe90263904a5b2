"""``torchtrack bench NAME``: throughput against a reference timed in the same run, one command module each in
this package (the workloads and references are library modules of ``torchtrack.bench``)."""

from torchtrack.bench._timing import BenchResult
from torchtrack.cli import add_subcommands
from torchtrack.cli._common import add_common_options, positive_int
from torchtrack.io.outputs import write_json
from torchtrack.threads import TRACKER_THREADS

NAME = "bench"
HELP = "measure throughput against a reference implementation timed in the same run"


def add_arguments(parser) -> None:
    add_subcommands(parser, "torchtrack.cli.bench", "workload", parser.get_default("_argv_rest") or [],
                    options=lambda p, _: add_common_options(p))


def run(args) -> int:
    return args._run(args)


def add_threads_option(parser) -> None:
    """``--threads`` of a filter's or tracker's bench, default :data:`torchtrack.threads.TRACKER_THREADS`."""
    parser.add_argument("--threads", type=positive_int, default=TRACKER_THREADS,
                        help=f"torch intra-op threads (default {TRACKER_THREADS}, as the trackers run in track: their "
                             "tensors are small, so more threads cost a fork and join per op and spin against "
                             "other work)")


def report(args, result: BenchResult, text: str) -> int:
    """Print a benchmark's ``text``, write its ``payload()`` to ``--json``; the exit status 0."""
    print(text)
    write_json(args.json, result.payload())
    return 0
