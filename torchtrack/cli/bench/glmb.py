"""``torchtrack bench glmb``: the options and the output of :mod:`torchtrack.bench.glmb`."""

import argparse

from torchtrack.bench import glmb
from torchtrack.cli._common import positive_int
from torchtrack.cli.bench import add_threads_option, report

NAME = "glmb"
HELP = "GLMB tracker frames/s at WPAFB scale against a per-hypothesis NumPy GLMB"
DESCRIPTION = """Frames per second of the glmb tracker at WPAFB scale against a NumPy delta-GLMB that loops over
hypotheses and tracks as the published codes do, timed in the same run.

Workload: 100 vehicles with constant-velocity motion in 1000 x 1000 px, detected with p_D 0.9 and 1 px
noise, Poisson clutter of mean 60 (about 150 measurements a frame). Both trackers start empty, run
--warmup frames untimed, then the timed frames one step at a time. Also printed: hypotheses, groups and
estimated tracks per frame of each.

Example: torchtrack bench glmb --frames 20
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--targets", type=positive_int, default=100, help="vehicles (default 100)")
    parser.add_argument("--warmup", type=int, default=10, help="untimed frames from the empty start (default 10)")
    parser.add_argument("--frames", type=positive_int, default=100, help="frames timed for torchtrack (default 100)")
    parser.add_argument("--reference-frames", type=positive_int, default=20,
                        help="frames timed for the NumPy reference (default 20)")
    parser.add_argument("--velocities", action="store_true", help="use the detector's velocities (default: positions)")
    add_threads_option(parser)


def run(args) -> int:
    result = glmb.measure(args.targets, args.warmup, args.frames, args.reference_frames, args.velocities,
                          args.threads, args.seed)
    return report(args, result, glmb.format_report(result))
