"""``torchtrack bench pf``: the options and the output of :mod:`torchtrack.bench.pf`."""

from torchtrack.bench import pf
from torchtrack.cli._common import positive_int
from torchtrack.cli.bench import add_threads_option, report

NAME = "pf"
HELP = "JTC particle-filter bank throughput (particle-steps/s) vs a vectorised NumPy implementation"
DESCRIPTION = """Throughput of the JTC paper's particle-filter bank (particle-steps per second) against the same
algorithm in vectorised NumPy, timed in the same run.

Workload: 2 classes x 5 motion modes, range-bearing radar, speed likelihoods and systematic resampling at
every scan, on the paper's trajectory: --runs runs x 2 classes x --particles particles x --scans scans.
The mean final probability of the true class is printed for both as a check.

Example: torchtrack bench pf --runs 4 --scans 20
"""


def add_arguments(parser) -> None:
    parser.add_argument("--runs", type=positive_int, default=20, help="Monte Carlo runs in one batch (default 20)")
    parser.add_argument("--particles", type=positive_int, default=3000, help="particles per class (default 3000)")
    parser.add_argument("--scans", type=positive_int, default=80, help="scans of the trajectory (default 80)")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32",
                        help="floating-point type of both implementations")
    add_threads_option(parser)
    parser.add_argument("--compile", action="store_true", help="torch.compile the filter step (inductor)")
    parser.add_argument("--repeats", type=positive_int, default=3, help="best of this many timed runs each (default 3)")


def run(args) -> int:
    result = pf.measure(args.runs, args.particles, args.scans, args.dtype, args.threads, args.compile, args.repeats,
                        args.seed)
    return report(args, result, pf.format_report(result))
