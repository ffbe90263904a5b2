"""``torchtrack bench pmb``: the options and the output of :mod:`torchtrack.bench.pmb`."""

import argparse

from torchtrack.bench import pmb
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import write_json

NAME = "pmb"
HELP = "TOMB/P filter scans/s (100 tracks, 150 measurements per scan) against a NumPy implementation"
DESCRIPTION = pmb.__doc__


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--targets", type=int, default=100, help="targets/tracks (default 100)")
    parser.add_argument("--measurements", type=int, default=150, help="measurements per scan (default 150)")
    parser.add_argument("--scans", type=int, default=20, help="timed scans (default 20)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    parser.add_argument("--lbp-iterations", type=int, default=30, help="LBP iteration cap (default 30)")
    parser.add_argument("--lbp-tol", type=float, default=1e-6,
                        help="LBP tolerance on the miss/new marginals (default 1e-6; 0: fixed iterations)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: on a shared, loaded machine more threads spin and "
                             "wait for each other)")
    parser.add_argument("--repeats", type=int, default=3)


def run(args) -> int:
    if args.targets < 1 or args.measurements < 1 or args.scans < 1:
        raise TorchtrackError("--targets, --measurements and --scans must be >= 1")
    result = pmb.measure(args.targets, args.measurements, args.scans, args.dtype, args.lbp_iterations, args.lbp_tol,
                         args.threads, args.repeats, args.seed)
    print(pmb.format_report(result, args.scans))
    write_json(args.json, result.payload())
    return 0
