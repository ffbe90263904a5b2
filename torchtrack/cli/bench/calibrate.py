"""``torchtrack bench calibrate``: the options and the output of :mod:`torchtrack.bench.calibrate`."""

import sys
from pathlib import Path

from torchtrack.cli._common import positive_float, positive_int, probability
from torchtrack.cli.bench import report

NAME = "calibrate"
HELP = "calibration from detections alone vs Optuna TPE with truth: held-out MOTA, HOTA, wall times"
DESCRIPTION = """The calibration from detections alone (torchtrack calibrate, no truth) against Optuna's TPE
search with the truth over 8 enhanced GM-PHD options, in one run: detections are simulated from --gt with
the sensor given, both fit on the training frames (--train), then each configuration (and the built-in
defaults) tracks the held-out frames (--test) from empty. By default Optuna gets as many tracker runs as the
calibration's tracker passes over the training frames (--trials to change). Optuna is optional
(pip install torchtrack-mtt[bench]); without it the reference is skipped with a message.

JSON keys: those of every bench plus calibrated_mota, reference_mota, defaults_mota (and _hota),
calibrate_seconds, reference_seconds, status (ok, retried, defaults), others_mota (the GLMB and the PMB,
calibrated and built-in), the fitted values and decisions.

Example (WPAFB AOI 02 truth from torchtrack convert-wpafb):
  torchtrack bench calibrate --gt out/wpafb/gt.txt --pd 0.7 --sigma 2.5 --clutter 100 \\
      --velocity-sigma 2.5 --image-size 585 496 --train 1 400 --test 401 512 --seed 0
"""


def add_arguments(parser) -> None:
    parser.add_argument("--gt", type=Path, required=True, help="truth, MOTChallenge text")
    parser.add_argument("--pd", type=probability, default=0.7, help="detection probability (default 0.7)")
    parser.add_argument("--sigma", type=positive_float, default=2.5, help="position noise in px (default 2.5)")
    parser.add_argument("--clutter", type=positive_float, default=100.0, help="false detections per frame")
    parser.add_argument("--velocity-sigma", type=positive_float, default=2.5,
                        help="velocity noise in px/frame (default 2.5)")
    parser.add_argument("--no-velocity", action="store_true", help="detections without velocities")
    parser.add_argument("--image-size", type=positive_float, nargs=2, default=None, metavar=("W", "H"),
                        help="clutter region (default: just covering the truth)")
    parser.add_argument("--train", type=positive_int, nargs=2, default=(1, 400), metavar=("A", "B"),
                        help="training frames (default 1 400)")
    parser.add_argument("--test", type=positive_int, nargs=2, default=(401, 512), metavar=("C", "D"),
                        help="held-out frames (default 401 512)")
    parser.add_argument("--trials", type=positive_int, default=None,
                        help="Optuna trials (default: the calibration's tracker passes)")


def run(args) -> int:
    from torchtrack.bench import calibrate
    from torchtrack.errors import TorchtrackError
    from torchtrack.io.mot import read_mot

    if args.train[0] > args.train[1] or args.test[0] > args.test[1]:
        raise TorchtrackError("--train/--test: the first frame must not exceed the last")
    gt = read_mot(args.gt)
    result = calibrate.measure(gt, args.pd, args.sigma, args.clutter,
                               None if args.no_velocity else args.velocity_sigma,
                               calibrate.as_image_size(args.image_size, gt), tuple(args.train), tuple(args.test),
                               args.trials, args.seed, progress=lambda s: print(f"bench calibrate: {s}",
                                                                                file=sys.stderr))
    return report(args, result, calibrate.format_report(result))
