"""``torchtrack bench detector``: the options and the output of :mod:`torchtrack.bench.detector`."""

import argparse
from pathlib import Path

from torchtrack.bench import detector
from torchtrack.cli._common import bounded, positive_int
from torchtrack.io.outputs import write_json

NAME = "detector"
HELP = "the detector's networks (reference weights in float and int8, other weights) on one frame's tiles: frames/s"
DESCRIPTION = """The detector's networks timed on the tiles that detection runs on one frame of each size, in
alternation, the fastest pass of each kept: the reference weights in float (the reference) and in int8, and with
--weights other weights in float and in int8 (int8 where a checkpoint carries a calibration; torchtrack
quantize-detector adds one). Prints each network's frames/s, its ratio to the reference and how far each int8
network's maps are from its float network's.

Example (about two minutes on a 2-core machine): compare weights you trained with the shipped ones
  torchtrack bench detector --weights out/detector.pt --sizes 512 2048 --repeats 5"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sizes", type=bounded(int, ge=64), nargs="+", default=list(detector.SIZES), metavar="S",
                        help=f"frame sides in px (default {' '.join(map(str, detector.SIZES))})")
    parser.add_argument("--repeats", type=positive_int, default=5,
                        help="timed passes of each network, alternated, the fastest kept (default 5)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--weights", type=Path, default=None,
                        help="other weights to time against the reference (default: none, the reference's int8 only)")
    parser.add_argument("--reference-weights", type=Path, default=None,
                        help="the reference weights (default: the shipped centertrack_small.pt)")


def run(args) -> int:
    results = []
    for size in args.sizes:
        result = detector.measure(size, args.repeats, args.seed, args.weights, args.threads, args.reference_weights)
        print(detector.format_report(result))
        results.append(result.payload())
    write_json(args.json, results if len(results) > 1 else results[0])
    return 0
