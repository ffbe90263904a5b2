"""``torchtrack simulate-detections``: detections from any ground truth (p_D, noise, clutter, velocity)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from torchtrack.cli._common import add_common_options, nonnegative_float, positive_float, positive_int, probability
from torchtrack.io.mot import POINT_BOX_SIZE, read_mot, write_motdata
from torchtrack.io.outputs import check_output_file, write_json
from torchtrack.metrics.table import format_table
from torchtrack.sim.detections import default_image_size, simulate_detections

NAME = "simulate-detections"
HELP = "simulate a detector on ground truth: misses, position noise, Poisson clutter, noisy velocities"
DESCRIPTION = """Simulate detections from ground truth (MOTChallenge text) and write them as MOTChallenge text
with id -1 (frame,-1,x,y,w,h,1,-1,-1,-1).

Each object is detected with probability --pd at its centre plus N(0, --sigma^2) noise per axis; each
frame gets Poisson(--clutter) false detections uniform over the image (--image-size W H, default: just
covering the truth). With --velocity-sigma V every detection carries a velocity in px/frame (the truth's
finite difference plus N(0, V^2) noise, standing in for the detector's velocity head), written in
columns 8 and 9: frame,-1,x,y,w,h,1,vx,vy,-1. Same --seed, same detections. The file appears whole
(written as OUT's .partial name, then renamed).

example (the WPAFB benchmark defaults):
  torchtrack simulate-detections --gt out/wpafb/gt.txt --pd 0.9 --sigma 1 --clutter 30 \\
      --velocity-sigma 1 --image-size 585 496 --seed 0 --out out/wpafb/det.txt
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gt", type=Path, required=True, help="ground truth, MOTChallenge text")
    parser.add_argument("--pd", type=probability, default=0.9, help="detection probability (default 0.9)")
    parser.add_argument("--sigma", type=positive_float, default=1.0, metavar="PX",
                        help="position noise standard deviation in px (default 1)")
    parser.add_argument("--clutter", type=nonnegative_float, default=30.0, metavar="N",
                        help="mean number of false detections per frame (default 30)")
    parser.add_argument("--velocity-sigma", type=positive_float, default=None, metavar="V",
                        help="add a velocity per detection with this noise in px/frame (default: none)")
    parser.add_argument("--image-size", type=positive_int, nargs=2, default=None, metavar=("W", "H"),
                        help="clutter region in px (default: just covering the truth centres)")
    parser.add_argument("--box", type=positive_float, default=POINT_BOX_SIZE,
                        help=f"box side in px written around each detection (default {POINT_BOX_SIZE:g})")
    parser.add_argument("--out", type=Path, required=True, help="detections file to write")
    add_common_options(parser)


def run(args: argparse.Namespace) -> int:
    check_output_file(args.out)
    truth = read_mot(args.gt)
    size = tuple(args.image_size) if args.image_size else default_image_size(truth)
    generator = torch.Generator().manual_seed(args.seed)
    sim = simulate_detections(truth, pd=args.pd, sigma=args.sigma, clutter=args.clutter, image_size=size,
                              velocity_sigma=args.velocity_sigma, generator=generator, box=args.box)
    write_motdata(args.out, sim.detections)
    frames = truth.frames()
    summary = {
        "frames": int(frames.max() - frames.min() + 1) if frames.size else 0,
        "detections": int(sim.detections.size),
        "true_detections": int((sim.source >= 0).sum()),
        "clutter": int((sim.source < 0).sum()),
        "truth_objects": int(truth.size),
        "image_size": list(size),
        "velocity": args.velocity_sigma is not None,
    }
    print(f"wrote {args.out}")
    print(format_table(list(summary)[:-2], [list(summary.values())[:-2]]))
    write_json(args.json, {**summary, "pd": args.pd, "sigma": args.sigma, "clutter_rate": args.clutter,
                           "velocity_sigma": args.velocity_sigma, "seed": args.seed,
                           "detected_fraction": float(np.mean(sim.source >= 0)) if sim.source.size else 0.0})
    return 0
