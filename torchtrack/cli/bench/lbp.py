"""``torchtrack bench lbp``: the options and the output of :mod:`torchtrack.bench.lbp`."""

import argparse

from torchtrack.bench import lbp
from torchtrack.cli.bench import add_threads_option, report
from torchtrack.errors import TorchtrackError

NAME = "lbp"
HELP = "LBP association marginals on n x n problems against a NumPy implementation"
DESCRIPTION = """Loopy belief propagation association marginals (Williams & Lau 2014) on n x n problems against the
same iteration written in NumPy, timed in the same run on the same problems.

Throughput is problems per second at the largest size; the time per problem of every size is printed
beside it.

Example: torchtrack bench lbp --sizes 10 100
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sizes", default="10,100,300,1000", help="comma-separated n (default %(default)s)")
    parser.add_argument("--iterations", type=int, default=15, help="LBP iterations (fixed; default 15)")
    parser.add_argument("--density", type=float, default=0.2,
                        help="fraction of track-measurement pairs inside the gate (default 0.2)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                        help="floating-point type of both implementations")
    add_threads_option(parser)
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats, best is kept (default 5)")


def run(args) -> int:
    try:
        sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    except ValueError as exc:
        raise TorchtrackError(f"--sizes must be comma-separated integers; got {args.sizes!r}") from exc
    if not sizes or min(sizes) < 1 or args.iterations < 1:
        raise TorchtrackError("--sizes must be positive integers and --iterations >= 1")
    result = lbp.measure(sizes, args.iterations, args.density, args.dtype, args.threads, args.repeats, args.seed)
    return report(args, result, lbp.format_report(result))
