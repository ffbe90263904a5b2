"""``torchtrack track``: run a multi-target tracker on detections or frames, write tracks and score them.

Every input goes through the same stream (:mod:`torchtrack.pipeline.replay`): a detection file through
:mod:`torchtrack.pipeline.detection_file`, frames through the video pipeline (:mod:`torchtrack.cli._frames`),
the WPAFB benchmark through :mod:`torchtrack.cli._wpafb_benchmark`.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from torchtrack.cli._common import (
    TRACKER_PRESETS,
    add_common_options,
    add_force_option,
    config_file,
    positive_float,
    positive_int,
    print_calibration,
)
from torchtrack.cli._frames import add_frame_options, frame_inputs_given, run_frame_inputs
from torchtrack.cli._strips import (
    add_strip_options,
    check_strip_arguments,
    rank_output,
    strip_group,
    strip_metrics,
    strip_tracker,
)
from torchtrack.cli._wpafb_benchmark import benchmark_config
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.options import read_tracker_sections
from torchtrack.filters.trackers.protocol import Tracker, tracker_names
from torchtrack.io.moving import SCORES, dont_care, flags_beside
from torchtrack.io.outputs import OutputFolder, write_json
from torchtrack.metrics.table import format_table1, protocol
from torchtrack.threads import torch_threads

if TYPE_CHECKING:
    import numpy as np

    from torchtrack.io.mot import MOTData
    from torchtrack.pipeline.config import PipelineConfig

NAME = "track"
OUTPUT = f"torchtrack {NAME}"
"""The command named in the marker of its output folders (:class:`torchtrack.io.outputs.OutputFolder`)."""
HELP = ("track the objects of a video, a folder of frames or a detection file with one of six trackers (gmphd, "
        "labelled-gmphd, sort, greedy, pmb, glmb) and score them")
DESCRIPTION = """Track the moving objects of a video (--video FILE) or a folder of frames (--frames DIR): each
frame is registered to the first, the detector finds the objects and the tracker (--tracker) follows them.
A MOTChallenge detection file (--detections DET) skips registration and detection; --sequences DIR runs
every sequence folder in DIR; --benchmark wpafb runs the WPAFB real-data benchmark end to end.

Scoring (--gt, --truth-csv, --sequences): the moving vehicles are the targets and the other objects
don't-care, as torchtrack eval --moving, torchtrack demo and the WPAFB benchmark score; --score all makes
every object a target (as eval without --moving). Every table names the protocol in its first line.

Trackers: gmphd (the enhanced GM-PHD, default), labelled-gmphd, sort, greedy, pmb and glmb. With --compare
every tracker (or those of --trackers) runs on the same detections and one table compares them.

Writes OUT/tracks.txt (MOTChallenge, one line per reported target), OUT/metrics.json (CLEAR-MOT and HOTA
against --gt at --threshold px, and the frames per second) and, from frames or a video, OUT/detections.txt
and OUT/annotated.mp4 (see torchtrack draw). The files appear in --out together when the run completes
(written in OUT.partial until then); an existing --out is replaced only when it holds the output of
torchtrack track (or with --force).

Examples:
  torchtrack track --video clip.mp4 --out out/clip
  torchtrack track --frames seq/frames --gt seq/gt.txt --tracker glmb --out out/seq
  torchtrack track --sequences out/val --compare --out out/val-compare
  torchtrack track --detections det.txt --gt gt.txt --compare --out out/compare
  torchtrack track --detections det.txt --gt gt.txt --params out/tune-gmphd/params.yaml
  torchtrack track --benchmark wpafb --out out/wpafb-benchmark
  OMP_NUM_THREADS=1 torchrun --standalone --nproc_per_node 2 -m torchtrack track --strips \\
      --frames seq/frames --gt seq/gt.txt --no-video --out out/strips   # each rank tracks a strip
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--detections", type=Path, metavar="DET", help="MOTChallenge detection file (id -1; "
                        "velocity vx, vy in columns 8-9 where the detector gives one)")
    parser.add_argument("--tracker", choices=tracker_names(), default="gmphd",
                        help="tracker (default gmphd: the enhanced GM-PHD)")
    parser.add_argument("--config", type=config_file(*TRACKER_PRESETS), default=None, metavar="YAML",
                        help="tracker options: a YAML mapping with one section per tracker name, a path or a "
                             "preset name (e.g. gmphd); defaults are the built-in values")
    parser.add_argument("--params", type=Path, default=None, metavar="FITTED",
                        help="fitted GM-PHD parameters from torchtrack tune (OUT/params.yaml): the tracker is "
                             "built from the file's options with the fitted values, exactly the tuned tracker "
                             "(with --detections; --tracker must be the file's, not with --config)")
    parser.add_argument("--calibrate", type=positive_int, default=None, metavar="N",
                        help="calibrate the trackers on the first N frames without truth (torchtrack calibrate; "
                             "with --frames/--video on the detections the pipeline gives its tracker there), then "
                             "track every frame with the result; OUT also holds track.yaml, calibration.json and "
                             "loss.png, and calibration.json's status says whether the fit passed its checks "
                             "(not with --config/--params/--sequences)")
    parser.add_argument("--gt", type=Path, default=None, help="ground truth (MOTChallenge) to score against")
    parser.add_argument("--score", choices=SCORES, default="moving",
                        help="which objects of the truth are targets: moving (default) the moving vehicles, the "
                             "others don't-care, as eval --moving, demo and the WPAFB benchmark score them (the "
                             "velocity.txt beside --gt where there is one, else those that moved more than 5 px "
                             "over the last 15 frames); all: every object, as eval without --moving")
    parser.add_argument("--out", type=Path, default=Path("out/track"), help="output folder (default out/track)")
    parser.add_argument("--threshold", type=positive_float, default=10.0, help="CLEAR-MOT centre distance in px "
                        "(default 10)")
    parser.add_argument("--compare", action="store_true", help="run every tracker and print the Table 1 "
                        "comparison")
    parser.add_argument("--trackers", nargs="+", choices=tracker_names(), default=None,
                        help="trackers for --compare / --benchmark (default: all)")
    parser.add_argument("--benchmark", type=benchmark_config, default=None, metavar="CONFIG",
                        help="run the WPAFB real-data benchmark: wpafb (the shipped preset), another preset "
                             "name or a config path")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch CPU threads of the detector and the "
                        "registration (default 1: the other core decodes and encodes); each tracker step runs on "
                        "the pipeline config's tracker_threads (default 1: its tensors are small)")
    parser.add_argument("--device", default="cpu", help="where the trackers run: cpu (default), cuda or cuda:N "
                        "(the detections are moved there frame by frame)")
    add_force_option(parser)
    add_common_options(parser)
    add_frame_options(parser)
    add_strip_options(parser)


def fitted_tracker(args: argparse.Namespace) -> Tracker:
    """The GM-PHD tracker of a ``torchtrack tune`` fitted-parameter file (``--params``): built from the
    file's tracker options and loaded with the fitted values exactly (:func:`torchtrack.tuning.tune.load_filter`)."""
    from torchtrack.tuning.config import read_params_file
    from torchtrack.tuning.tune import load_filter

    doc = read_params_file(args.params, ("gmphd",), "torchtrack track --params")
    kind = (doc.get("model") or {}).get("tracker", "gmphd")
    if kind != args.tracker:
        raise TorchtrackError(f"{args.params}: fitted for --tracker {kind}; got --tracker {args.tracker}")
    given = {"--config": args.config, "--compare": args.compare, "--benchmark": args.benchmark,
             "--video/--frames/--sequences": args.video or args.frames or args.sequences}
    clash = [flag for flag, value in given.items() if value]
    if clash:
        raise TorchtrackError(f"--params sets the whole tracker and runs on --detections; it does not combine "
                              f"with {', '.join(clash)}")
    tracker = load_filter(args.params)
    tracker.reset()
    return tracker


def inputs(args: argparse.Namespace) -> list[Path | None]:
    """The files and folders ``torchtrack track`` reads (none of them may lie in its output folder)."""
    return [args.detections, args.gt, args.config, args.params, args.pipeline_config, args.video, args.frames,
            args.sequences, args.weights, args.camera, args.truth_csv]


def check_arguments(args: argparse.Namespace) -> None:
    """The argument errors that need no file (before anything is read or written)."""
    if not (math.isfinite(args.threshold) and args.threshold > 0):
        raise TorchtrackError(f"--threshold must be a positive distance in px, got {args.threshold:g}")
    check_strip_arguments(args, frame_inputs_given(args))
    if args.compare and args.detections is not None and args.gt is None:
        raise TorchtrackError("--compare needs --gt to score the trackers")
    if args.calibrate is not None:
        clash = [flag for flag, value in (("--config", args.config), ("--params", args.params),
                                          ("--compare", args.compare), ("--benchmark", args.benchmark),
                                          ("--strips", args.strips)) if value]
        if args.sequences:
            clash.append("--sequences")
        if clash or not (args.detections or args.frames or args.video):
            raise TorchtrackError("--calibrate needs --detections, --frames or --video and sets the trackers' "
                                  f"options itself; it does not combine with {', '.join(clash) or 'no input'}")


def run(args: argparse.Namespace) -> int:
    check_arguments(args)
    with torch_threads(args.threads):
        torch.manual_seed(args.seed)
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from torchtrack.io.mot import read_mot
    from torchtrack.pipeline.api import track
    from torchtrack.pipeline.config import load_pipeline_config
    from torchtrack.pipeline.detection_file import compare, detection_file_config

    fitted = fitted_tracker(args) if args.params is not None else None
    tracker_options = read_tracker_sections(args.config)
    if frame_inputs_given(args):
        return run_frame_inputs(args, OUTPUT, tracker_options.get(args.tracker), inputs(args))
    if args.benchmark is not None:
        from torchtrack.cli._wpafb_benchmark import run_benchmark

        with OutputFolder(args.out, OUTPUT, args.force, inputs=inputs(args)) as staging:
            payload = run_benchmark(args.benchmark, staging, args.seed, args.trackers, args.config)
        write_json(args.json, payload)
        return 0
    if args.detections is None:
        raise TorchtrackError("give an input: --video FILE, --frames DIR, --sequences DIR, --detections DET "
                              "or --benchmark CONFIG")
    base = load_pipeline_config(args.pipeline_config) if args.pipeline_config else None
    config = detection_file_config(tracker_options, args.threshold, base).replace(device=args.device)
    if args.strips:
        return _run_strips(args, config, fitted)
    if args.calibrate is not None:
        return _run_calibrated(args, base)
    if not args.compare:
        result = track(detections=args.detections, tracker=fitted or args.tracker, tracker_name=args.tracker,
                       config=tracker_options, gt=args.gt, score=args.score, device=args.device,
                       threshold=args.threshold,
                       pipeline_config=base, out=args.out, force=args.force, inputs=inputs(args))
        _print_report(args, result.report, args.gt is not None)
        return 0
    with OutputFolder(args.out, OUTPUT, args.force, inputs=inputs(args)) as staging:
        det = read_mot(args.detections)
        gt = read_mot(args.gt) if args.gt is not None else None
        report = compare(det, config, staging, gt, args.trackers or tracker_names(), _dont_care(args, gt))
        write_json(staging / "comparison.json", report)
    _print_report(args, report, gt is not None)
    return 0


def _run_calibrated(args: argparse.Namespace, base: PipelineConfig | None) -> int:
    """``--calibrate N``: calibrate on the first N frames of ``--detections``, track all of them with the result."""
    from torchtrack.calibrated_track import track

    tracked = track(detections=args.detections, calibrate=args.calibrate, seed=args.seed, tracker=args.tracker,
                    gt=args.gt, score=args.score, device=args.device, threshold=args.threshold,
                    pipeline_config=base, progress=True, out=args.out, force=args.force)
    print_calibration(tracked.calibration)
    _print_report(args, tracked.report, args.gt is not None)
    return 0


def _run_strips(args: argparse.Namespace, config: PipelineConfig, fitted: Tracker | None) -> int:
    """``--strips``: one tracker over the strips of the torchrun ranks; rank 0 writes and prints."""
    from torchtrack.filters.trackers.protocol import make_tracker
    from torchtrack.io.mot import read_mot
    from torchtrack.pipeline.detection_file import track_detections

    det = read_mot(args.detections)
    gt = read_mot(args.gt) if args.gt is not None else None
    with strip_group() as rank:
        tracker = strip_tracker(fitted or make_tracker(args.tracker, config.options_for(args.tracker)), det, args)
        with rank_output(rank, args.out, OUTPUT, args.force, inputs(args)) as staging:
            report = track_detections(det, args.tracker, config, staging, gt, tracker, _dont_care(args, gt))
            report.update(strip_metrics(tracker))
            if rank == 0:
                write_json(staging / "metrics.json", report)
    if rank == 0:
        _print_report(args, report, gt is not None)
    return 0


def _dont_care(args: argparse.Namespace, gt: MOTData | None) -> np.ndarray | None:
    """The don't-care lines of ``--gt`` under ``--score`` (:func:`torchtrack.io.moving.dont_care`)."""
    return dont_care(gt, args.score, flags_beside(args.gt)) if gt is not None else None


def _print_report(args: argparse.Namespace, report: dict, scored: bool) -> None:
    if args.compare or scored:
        print(format_table1(report if args.compare else {args.tracker: report},
                            protocol(args.score == "moving", args.threshold)))
    else:
        print(f"{args.tracker}: {report['frames_run']} frames, {report['FPS']:.1f} frames/s; tracks in "
              f"{args.out / 'tracks.txt'}")
    write_json(args.json, report)
