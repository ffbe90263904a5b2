"""``torchtrack bench detector``: the options and the output of :mod:`torchtrack.bench.detector`."""

import argparse
from pathlib import Path

from torchtrack.bench import detector
from torchtrack.cli._common import bounded, positive_int
from torchtrack.io.outputs import write_json

NAME = "detector"
HELP = "the detector's network in int8 vs float (the same weights) on one frame's tiles: frames/s and the ratio"
DESCRIPTION = """The detector's network in float and in int8 (the same weights), timed on the tiles that detection
runs on one frame of each size, in alternation, the fastest pass of each kept; prints both rates, their ratio
and how far the int8 maps are from the float ones.

The weights must carry an int8 calibration (the shipped ones do; torchtrack quantize-detector adds one).
A quick run on a 2-core machine (about a minute): --sizes 512 2048 --repeats 5"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sizes", type=bounded(int, ge=64), nargs="+", default=list(detector.SIZES), metavar="S",
                        help=f"frame sides in px (default {' '.join(map(str, detector.SIZES))})")
    parser.add_argument("--repeats", type=positive_int, default=5,
                        help="timed passes of each network, alternated, the fastest kept (default 5)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--weights", type=Path, default=None, help="checkpoint (default: the shipped weights)")


def run(args) -> int:
    results = []
    for size in args.sizes:
        result = detector.measure(size, args.repeats, args.seed, args.weights, args.threads)
        print(detector.format_report(result))
        results.append(result.payload())
    write_json(args.json, results if len(results) > 1 else results[0])
    return 0
