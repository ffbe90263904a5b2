"""``torchtrack bench kf``: the options and the output of :mod:`torchtrack.bench.kf`."""

from torchtrack.bench import kf
from torchtrack.cli.bench import add_threads_option, report

NAME = "kf"
HELP = "batched Kalman filter throughput vs NumPy and a per-track loop"
DESCRIPTION = """Batched Kalman filter throughput (track-steps per second) against a batched NumPy implementation of
the same equations, timed in the same run.

Workload: 2-D nearly-constant-velocity targets (state x, y, vx, vy), position measurements, float32,
--tracks tracks over --steps steps. Also printed: the general path (full 4 x 4 matrices, compiled unless
--no-compile) and FilterPy's Kalman filter run one track at a time on --loop-tracks tracks, where FilterPy is
installed.

Example: torchtrack bench kf --tracks 10000 --steps 20
"""


def add_arguments(parser) -> None:
    parser.add_argument("--tracks", type=int, default=100_000, help="tracks (default 100000)")
    parser.add_argument("--steps", type=int, default=100, help="time steps (default 100)")
    parser.add_argument("--general-steps", type=int, default=10, help="steps timed for the general path")
    parser.add_argument("--loop-tracks", type=int, default=200, help="tracks for the per-track loop")
    parser.add_argument("--no-compile", action="store_true", help="time the eager fast and general paths")
    add_threads_option(parser)


def run(args) -> int:
    result = kf.measure(args.tracks, args.steps, args.general_steps, args.loop_tracks, not args.no_compile,
                        args.seed, args.threads)
    return report(args, result, kf.format_report(result))
