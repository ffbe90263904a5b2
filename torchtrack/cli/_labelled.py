"""``--images DIR (--gt FILE | --truth-csv FILE) [--region X0 Y0 X1 Y1]``: labelled real frames for
``train-detector --finetune`` and ``eval-detector``, registered as the pipeline registers them."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def add_labelled_options(parser: argparse.ArgumentParser, purpose: str) -> None:
    """The options of the module docstring; ``purpose`` ends the help of ``--images``."""
    parser.add_argument("--images", type=Path, default=None, metavar="DIR",
                        help=f"folder of labelled frames (image k is truth frame k, from 1) {purpose}")
    truth = parser.add_mutually_exclusive_group()
    truth.add_argument("--gt", type=Path, default=None, metavar="FILE",
                       help="point truth of --images as MOTChallenge gt.txt (box centres)")
    truth.add_argument("--truth-csv", type=Path, default=None, metavar="FILE",
                       help="point truth of --images as the WPAFB truth CSV (its first row is frame 1)")
    parser.add_argument("--region", type=int, nargs=4, default=None, metavar=("X0", "Y0", "X1", "Y1"),
                        help="labelled pixels x0 <= x < x1, y0 <= y < y1 (default: the whole frame); outside "
                             "it nothing counts")


def check_labelled_options(args: argparse.Namespace) -> None:
    """Truth or a region without ``--images``, or ``--images`` without truth: an error naming the option."""
    from torchtrack.errors import TorchtrackError

    given = [name for name in ("gt", "truth_csv", "region") if getattr(args, name) is not None]
    if args.images is None and given:
        raise TorchtrackError(f"--{given[0].replace('_', '-')} needs --images")
    if args.images is not None and args.gt is None and args.truth_csv is None:
        raise TorchtrackError("--images needs its truth: --gt FILE or --truth-csv FILE")


def load_labelled(args: argparse.Namespace, registration: str):
    """``(LabelledFrames, Region)`` of the options, each frame registered onto its predecessor with the
    pipeline's registration (``registration``: its method, lk | orb | none)."""
    from torchtrack.detector.labelled import label_frames, read_images
    from torchtrack.detector.region import check_region
    from torchtrack.io.mot import read_mot
    from torchtrack.io.wpafb import read_wpafb_csv
    from torchtrack.pipeline.registration import Registration, RegistrationConfig

    frames = read_images(args.images)
    source = args.gt if args.gt is not None else args.truth_csv
    truth = read_mot(source) if args.gt is not None else read_wpafb_csv(source)
    data = label_frames(frames, truth, str(source))              # checks the truth before registering
    region = check_region(args.region, frames.shape[1:])
    register = Registration(RegistrationConfig(method=registration))
    to_reference = [register(f).homography for f in frames]
    motions = [np.eye(3)] + [np.linalg.inv(a) @ b for a, b in zip(to_reference[:-1], to_reference[1:])]
    return data._replace(motions=motions), region
