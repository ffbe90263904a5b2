"""``torchtrack bench registration``: the options and the output of :mod:`torchtrack.bench.registration`."""

from torchtrack.bench import registration
from torchtrack.cli.bench import report

NAME = "registration"
HELP = "registration frames/s and error vs the true camera motion (ours LK vs OpenCV ORB+RANSAC)"
DESCRIPTION = """Frame registration speed and accuracy on synthetic sequences with a known camera motion, against
OpenCV's classic feature pipeline (ORB features, brute-force matching, RANSAC homography), timed in the
same run on the same frames.

Ours: keyframe corners, Lucas-Kanade tracking and RANSAC. Also printed: the error of each against the true
camera motion (median transfer error on a 16 px grid) and of ours with ECC refinement.

Example: torchtrack bench registration --sequences 2 --frames 10
"""


def add_arguments(parser) -> None:
    parser.add_argument("--sequences", type=int, default=3, help="synthetic sequences (default 3)")
    parser.add_argument("--frames", type=int, default=30, help="frames per sequence (default 30)")
    parser.add_argument("--size", type=int, default=512, help="frame side in px (default 512)")


def run(args) -> int:
    result = registration.measure(args.sequences, args.frames, args.size, args.seed)
    return report(args, result, registration.format_report(result))
