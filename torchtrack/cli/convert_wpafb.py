"""``torchtrack convert-wpafb``: the WPAFB truth CSV to MOTChallenge text."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from torchtrack.cli._common import add_common_options, positive_float
from torchtrack.io.mot import POINT_BOX_SIZE, write_motdata
from torchtrack.io.moving import moving_mask
from torchtrack.io.outputs import check_output_file, write_json
from torchtrack.io.wpafb import read_wpafb_csv
from torchtrack.metrics.table import format_table

NAME = "convert-wpafb"
HELP = "convert the WPAFB truth CSV (transformed_object_states.csv) to MOTChallenge text"
DESCRIPTION = f"""Convert the WPAFB 2009 truth CSV to MOTChallenge text (frame,id,x,y,w,h,1,-1,-1,-1).

The CSV's px is the image row and py the column; objects at (0, 0) are absent; the trailing all-zero
row is skipped. Each vehicle becomes a {POINT_BOX_SIZE:g} x {POINT_BOX_SIZE:g} px box centred on it
(--box). Frames are renumbered from 1 unless --keep-frame-numbers. The file appears whole (written under
a .partial name, then renamed).

example:
  torchtrack data fetch wpafb
  torchtrack convert-wpafb data/wpafb-aoi02/transformed_object_states.csv --out out/wpafb/gt.txt
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("csv", type=Path, help="transformed_object_states.csv")
    parser.add_argument("--out", type=Path, required=True, help="MOTChallenge text file to write")
    parser.add_argument("--keep-frame-numbers", action="store_true",
                        help="keep the CSV's frame numbers (100-611 for AOI 02) instead of 1, 2, ...")
    parser.add_argument("--box", type=positive_float, default=POINT_BOX_SIZE,
                        help=f"box side in px around each vehicle (default {POINT_BOX_SIZE:g})")
    add_common_options(parser, random=False)


def run(args: argparse.Namespace) -> int:
    check_output_file(args.out)
    truth = read_wpafb_csv(args.csv, keep_frame_numbers=args.keep_frame_numbers, box=args.box)
    write_motdata(args.out, truth)
    frames = truth.frames()
    per_frame = np.bincount(truth.frame - frames.min()) if truth.size else np.zeros(1, int)
    moving = moving_mask(truth)
    summary = {
        "frames": int(frames.size),
        "first_frame": int(frames.min()) if frames.size else None,
        "last_frame": int(frames.max()) if frames.size else None,
        "ids": int(np.unique(truth.id).size),
        "objects": int(truth.size),
        "mean_per_frame": float(per_frame[per_frame > 0].mean()) if truth.size else 0.0,
        "max_per_frame": int(per_frame.max()),
        "moving_objects": int(moving.sum()),
        "moving_ids": int(np.unique(truth.id[moving]).size),
        "out": str(args.out),
    }
    print(f"wrote {args.out}")
    print(format_table(list(summary)[:-1], [list(summary.values())[:-1]], floatfmt=".1f"))
    write_json(args.json, summary)
    return 0
