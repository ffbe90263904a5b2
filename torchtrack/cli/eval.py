"""``torchtrack eval``: CLEAR-MOT, MT/PT/ML, FRAG, IDF1 and HOTA of a tracker output against ground truth."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from torchtrack.cli._common import add_common_options, bounded, positive_float
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import read_mot
from torchtrack.io.moving import flags_beside
from torchtrack.io.outputs import write_json
from torchtrack.metrics.clear_mot import KEYS
from torchtrack.metrics.evaluation import (
    OSPA_KEYS,
    EvalOptions,
    benchmark_sequences,
    combine,
    evaluate,
    evaluate_scores,
)
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

--moving scores only the moving vehicles (the paper's evaluation), as track, demo and the WPAFB benchmark
do: where a velocity.txt of simulate-video lies beside gt.txt, the vehicles it flags as driving; otherwise
the objects that moved more than 5 px over the last 15 frames. The other objects are don't-care:
predictions matched to them are ignored, not counted as false.

A whole benchmark in the MOTChallenge layout: --gt-folder DIR with DIR/SEQ/gt/gt.txt for every sequence,
--pred-folder DIR with the tracker's DIR/SEQ.txt; one row per sequence and a COMBINED row, combined as
TrackEval combines sequences (CLEAR-MOT and IDF1 from summed counts; HOTA from summed per-alpha counts with
AssA/AssRe/AssPr/LocA weighted by each sequence's TP). The JSON then holds {"sequences": {SEQ: scores},
"combined": scores}.

examples:
  torchtrack eval --gt gt.txt --pred out/tracks.txt --threshold 10 --json out/eval.json
  torchtrack eval --gt-folder data/MOT17/train --pred-folder out/mot17 --iou 0.5 --json out/mot17.json
"""

PERCENT = ("MOTA", "IDF1", "precision", "recall")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gt", type=Path, help="ground truth, MOTChallenge text")
    parser.add_argument("--pred", type=Path, help="tracker output, MOTChallenge text")
    parser.add_argument("--gt-folder", type=Path, metavar="DIR",
                        help="a whole benchmark instead: DIR/SEQ/gt/gt.txt for every sequence SEQ")
    parser.add_argument("--pred-folder", type=Path, metavar="DIR",
                        help="with --gt-folder: the tracker output DIR/SEQ.txt of every sequence")
    gate = parser.add_mutually_exclusive_group()
    gate.add_argument("--threshold", type=positive_float, default=10.0, metavar="PX",
                      help="centre-distance gate in pixels (default 10)")
    gate.add_argument("--iou", type=bounded(float, gt=0, le=1), default=None, metavar="T",
                      help="IoU gate instead (e.g. 0.5)")
    parser.add_argument("--moving", action="store_true",
                        help="score only moving vehicles: those flagged in the velocity.txt beside gt.txt, else those "
                             "that moved more than 5 px over the last 15 frames, as track --score moving (its default) "
                             "scores (default here: all objects)")
    parser.add_argument("--count-zero-conf", action="store_true",
                        help="score ground-truth lines with conf 0 as objects (default: ignored, as MOTChallenge)")
    parser.add_argument("--ospa", type=positive_float, default=None, metavar="C",
                        help="also report the mean per-frame OSPA (p=1) and GOSPA (p=2, alpha=2) of the "
                             "centres with cut-off C px")
    add_common_options(parser, random=False)


def _percent(key: str, value: float) -> float:
    return 100 * value if key in PERCENT or key in HOTA_KEYS else value


def format_rows(rows: dict[str, dict], keys: Sequence[str], floatfmt: str = ".2f") -> str:
    """One table row per entry of ``rows`` (name → scores; the name column only when there are several),
    the columns ``keys``, ratios in percent."""
    header = [f"{key}%" if key in PERCENT or key in HOTA_KEYS else key for key in keys]
    table = [[_percent(key, scores[key]) for key in keys] for scores in rows.values()]
    if len(rows) > 1:
        header, table = ["sequence", *header], [[name, *row] for name, row in zip(rows, table)]
    return format_table(header, table, floatfmt=floatfmt)


def _options(args: argparse.Namespace) -> EvalOptions:
    single = (args.gt is not None, args.pred is not None)
    folders = (args.gt_folder is not None, args.pred_folder is not None)
    if not (all(single) and not any(folders) or all(folders) and not any(single)):
        raise TorchtrackError("give --gt and --pred, or --gt-folder and --pred-folder")
    return EvalOptions(args.threshold, args.iou, args.moving, args.count_zero_conf, args.ospa)


def run(args: argparse.Namespace) -> int:
    options = _options(args)
    if args.gt is not None:
        pairs = [("", args.gt, args.pred)]
        print(f"{args.pred} vs {args.gt}: {options.protocol}")
    else:
        pairs = benchmark_sequences(args.gt_folder, args.pred_folder)
        print(f"{args.pred_folder} vs {args.gt_folder}: {len(pairs)} sequences, {options.protocol}")
    if args.gt is not None:
        rows = {"": evaluate_scores(args.gt, args.pred, threshold=options.threshold, iou=options.iou,
                                    moving=options.moving, count_zero_conf=options.count_zero_conf,
                                    ospa=options.ospa)}
    else:
        evaluations = {name: evaluate(read_mot(gt), read_mot(pred), options, flags_beside(gt))
                       for name, gt, pred in pairs}
        if len(pairs) > 1:
            evaluations["COMBINED"] = combine(list(evaluations.values()))
        rows = {name: e.scores() for name, e in evaluations.items()}
    print(format_rows(rows, KEYS))
    print(format_rows(rows, HOTA_KEYS))
    if options.ospa is not None:
        print(f"mean per frame, cut-off {options.ospa:g} px (GOSPA parts in px^2)")
        print(format_rows(rows, OSPA_KEYS, floatfmt=".3f"))
    about = {"gate": options.gate, "moving_only": bool(args.moving)}
    if args.gt is not None:
        write_json(args.json, rows[""])
    else:
        combined = rows.pop("COMBINED") if len(pairs) > 1 else next(iter(rows.values()))
        write_json(args.json, {"sequences": rows, "combined": combined, **about})
    return 0
