"""``torchtrack bench pmb``: the options and the output of :mod:`torchtrack.bench.pmb`."""

import argparse

from torchtrack.bench import pmb
from torchtrack.cli._common import positive_int
from torchtrack.cli.bench import add_threads_option, report

NAME = "pmb"
HELP = "TOMB/P filter scans/s (100 tracks, 150 measurements per scan) against a NumPy implementation"
DESCRIPTION = """TOMB/P filter scans per second with 100 tracks and 150 measurements per scan against the same
filter step written in NumPy, timed in the same run on the same scans.

100 targets move at constant velocity; each scan holds their detections (p_D 0.9) topped up with uniform
clutter to 150 measurements. After a warm-up that confirms the tracks, each timed scan is a prediction and
an update (gating, LBP association, merging and pruning).

Example: torchtrack bench pmb --scans 10
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--targets", type=positive_int, default=100, help="targets/tracks (default 100)")
    parser.add_argument("--measurements", type=positive_int, default=150, help="measurements per scan (default 150)")
    parser.add_argument("--scans", type=positive_int, default=20, help="timed scans (default 20)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64",
                        help="floating-point type of both implementations")
    parser.add_argument("--lbp-iterations", type=int, default=30, help="LBP iteration cap (default 30)")
    parser.add_argument("--lbp-tol", type=float, default=1e-6,
                        help="LBP tolerance on the miss/new marginals (default 1e-6; 0: fixed iterations)")
    add_threads_option(parser)
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats, the fastest kept")


def run(args) -> int:
    result = pmb.measure(args.targets, args.measurements, args.scans, args.dtype, args.lbp_iterations, args.lbp_tol,
                         args.threads, args.repeats, args.seed)
    return report(args, result, pmb.format_report(result, args.scans))
