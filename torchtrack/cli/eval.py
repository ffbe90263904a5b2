"""``torchtrack eval``: CLEAR-MOT, MT/PT/ML, FRAG, IDF1 and HOTA of a tracker output against ground truth."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from torchtrack.cli._common import add_common_options, bounded, positive_float
from torchtrack.io.mot import read_mot
from torchtrack.io.outputs import write_json
from torchtrack.io.wpafb import moving_mask
from torchtrack.metrics import clear_mot, drop_ignored, hota, mot_ospa_gospa
from torchtrack.metrics.clear_mot import KEYS
from torchtrack.metrics.hota import KEYS as HOTA_KEYS
from torchtrack.metrics.table import format_table

NAME = "eval"
HELP = "score tracks (MOTChallenge text) against ground truth: CLEAR-MOT, MT/PT/ML, IDF1, HOTA"
DESCRIPTION = """Score a tracker output against ground truth, both MOTChallenge text files.

Matching: per frame, correspondences of the previous frames are kept while still within the gate, the
rest are assigned by the Hungarian algorithm (Bernardin & Stiefelhagen, as py-motmetrics implements it).
The gate is a centre distance (--threshold PX, default 10, the paper's) or an IoU (--iou T).
MOTA, MOTP, IDF1, precision and recall are printed in percent; the JSON holds fractions
(keys MOTA, MOTP, IDF1, MT, PT, ML, FP, FN, IDS, FRAG, TP, GT, precision, recall, frames, ...).
MOTP is the mean matched distance in pixels (centre mode) or the mean 1 - IoU (IoU mode).

HOTA (Luiten et al. 2021, as TrackEval computes it) is printed in a second table, in percent, and written
as the JSON keys HOTA, DetA, AssA, LocA, DetRe, DetPr, AssRe, AssPr (fractions, means over alpha = 0.05 ...
0.95). Its similarity is the IoU with --iou, else max(0, 1 - d / PX) of the centre distance d.

Ground-truth lines with conf 0 are don't-care objects, as in MOTChallenge and TrackEval: a prediction
matched to one is dropped (neither a hit nor a false positive); --count-zero-conf scores them as objects.

--moving keeps only ground-truth objects that moved more than 5 px over the last 15 frames (the
paper's evaluation); predictions matched to the other objects are ignored, not counted as false.

example:
  torchtrack eval --gt gt.txt --pred out/tracks.txt --threshold 10 --json out/eval.json
"""

PERCENT = ("MOTA", "IDF1", "precision", "recall")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gt", type=Path, required=True, help="ground truth, MOTChallenge text")
    parser.add_argument("--pred", type=Path, required=True, help="tracker output, MOTChallenge text")
    gate = parser.add_mutually_exclusive_group()
    gate.add_argument("--threshold", type=positive_float, default=10.0, metavar="PX",
                      help="centre-distance gate in pixels (default 10)")
    gate.add_argument("--iou", type=bounded(float, gt=0, le=1), default=None, metavar="T",
                      help="IoU gate instead (e.g. 0.5)")
    parser.add_argument("--moving", action="store_true",
                        help="score only objects that moved > 5 px over the last 15 frames (paper's rule)")
    parser.add_argument("--count-zero-conf", action="store_true",
                        help="score ground-truth lines with conf 0 as objects (default: ignored, as MOTChallenge)")
    parser.add_argument("--ospa", type=positive_float, default=None, metavar="C",
                        help="also report the mean per-frame OSPA (p=1) and GOSPA (p=2, alpha=2) of the "
                             "centres with cut-off C px")
    add_common_options(parser)


def format_scores(scores: dict) -> str:
    """The scores as one table row, ratios in percent."""
    header, row = [], []
    for key in KEYS:
        value = scores[key]
        if key in PERCENT:
            header.append(f"{key}%")
            row.append(100 * value if not math.isnan(value) else value)
        else:
            header.append(key)
            row.append(value)
    return format_table(header, [row], floatfmt=".2f")


def format_hota(scores: dict) -> str:
    """The HOTA scores as one table row, in percent."""
    return format_table([f"{key}%" for key in HOTA_KEYS], [[100 * scores[key] for key in HOTA_KEYS]],
                        floatfmt=".2f")


def run(args: argparse.Namespace) -> int:
    gt, pred = read_mot(args.gt), read_mot(args.pred)
    if args.moving:
        gt, pred = drop_ignored(gt, pred, ~moving_mask(gt), threshold=args.threshold, iou=args.iou)
    scores = clear_mot(gt, pred, threshold=args.threshold, iou=args.iou, count_zero_conf=args.count_zero_conf)
    gate = f"IoU >= {args.iou}" if args.iou is not None else f"centre distance <= {args.threshold} px"
    print(f"{args.pred} vs {args.gt} ({gate}{', moving objects only' if args.moving else ''})")
    print(format_scores(scores))
    hota_scores = hota(gt, pred, threshold=args.threshold, iou=args.iou, count_zero_conf=args.count_zero_conf)
    print(format_hota(hota_scores))
    scores.update({key: hota_scores[key] for key in HOTA_KEYS})
    if args.ospa is not None:
        _, o, g = mot_ospa_gospa(gt, pred, c=args.ospa, p_ospa=1.0, p_gospa=2.0)
        om, gm = o.mean(), g.mean()
        sets = {"OSPA": om["total"], "OSPA_localisation": om["localisation"], "OSPA_cardinality": om["cardinality"],
                "GOSPA": gm["total"], "GOSPA_localisation": gm["localisation"], "GOSPA_missed": gm["missed"],
                "GOSPA_false": gm["false"]}
        print(f"mean per frame, cut-off {args.ospa:g} px (GOSPA parts in px^2)")
        print(format_table(list(sets), [list(sets.values())], floatfmt=".3f"))
        scores.update(sets)
    write_json(args.json, {**scores, "gate": gate, "moving_only": bool(args.moving)})
    return 0
