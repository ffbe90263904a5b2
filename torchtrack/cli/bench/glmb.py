"""``torchtrack bench glmb``: the options and the output of :mod:`torchtrack.bench.glmb`."""

import argparse

from torchtrack.bench import glmb
from torchtrack.cli._common import positive_int
from torchtrack.cli.bench import report

NAME = "glmb"
HELP = "GLMB tracker frames/s at WPAFB scale against a per-hypothesis NumPy GLMB"
DESCRIPTION = glmb.__doc__


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--targets", type=positive_int, default=100, help="vehicles (default 100)")
    parser.add_argument("--warmup", type=int, default=10, help="untimed frames from the empty start (default 10)")
    parser.add_argument("--frames", type=positive_int, default=100, help="frames timed for torchtrack (default 100)")
    parser.add_argument("--reference-frames", type=positive_int, default=20,
                        help="frames timed for the NumPy reference (default 20)")
    parser.add_argument("--velocities", action="store_true", help="use the detector's velocities (default: positions)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")


def run(args) -> int:
    result = glmb.measure(args.targets, args.warmup, args.frames, args.reference_frames, args.velocities,
                          args.threads, args.seed)
    return report(args, result, glmb.format_report(result))
