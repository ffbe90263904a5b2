"""``torchtrack bench registration``: the options and the output of :mod:`torchtrack.bench.registration`."""

from torchtrack.bench import registration
from torchtrack.cli.bench import report

NAME = "registration"
HELP = "registration frames/s and error vs the true camera motion (ours LK vs OpenCV ORB+RANSAC)"
DESCRIPTION = registration.__doc__


def add_arguments(parser) -> None:
    parser.add_argument("--sequences", type=int, default=3, help="synthetic sequences (default 3)")
    parser.add_argument("--frames", type=int, default=30, help="frames per sequence (default 30)")
    parser.add_argument("--size", type=int, default=512, help="frame side in px (default 512)")


def run(args) -> int:
    result = registration.measure(args.sequences, args.frames, args.size, args.seed)
    return report(args, result, registration.format_report(result))
