"""The frame-input options of ``torchtrack track``: ``--video FILE``, ``--frames DIR``, ``--sequences DIR``.

``torchtrack/cli/track.py`` calls :func:`add_frame_options` on its parser and, when one of them was given,
:func:`run_frame_inputs` with its parsed arguments (it also reads ``--tracker``, ``--gt``, ``--out``,
``--force``, ``--json``, ``--threads``, ``--compare``, ``--trackers``, ``--strips``, ``--band`` and
``--strip-height`` of ``torchtrack track``); the tracker's options come from ``torchtrack track --config``
through ``tracker_options``. The output folder is written as one set (:class:`~torchtrack.io.outputs.OutputFolder`;
under ``torchrun`` every rank writes into the same staging folder,
:func:`~torchtrack.pipeline.sequences.shared_output`). With ``--strips`` (:mod:`torchtrack.cli._strips`) the
ranks split every frame into strips and rank 0 alone writes the folder.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from torchtrack.calibrated_track import track
from torchtrack.cli._common import PIPELINE_PRESETS, config_file, print_calibration
from torchtrack.cli._strips import frame_strips, rank_output, strip_group, strip_metrics
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import tracker_names
from torchtrack.io.frames import open_frames
from torchtrack.io.mot import MOTData, read_mot
from torchtrack.io.moving import dont_care, flags_beside
from torchtrack.io.outputs import OutputFolder, write_json
from torchtrack.metrics.table import TABLE1_HEADER, format_table, format_table1, protocol, table1_row
from torchtrack.pipeline.config import PipelineConfig, load_pipeline_config
from torchtrack.pipeline.sequences import destroy, run_sequences, shared_output
from torchtrack.pipeline.track_video import track_video
from torchtrack.pipeline.truth import wpafb_truth
from torchtrack.sim.video import read_camera

HEADER = ["sequence", *TABLE1_HEADER[1:-1], "FPS (end to end)"]
"""The columns of Table 1 (:func:`~torchtrack.metrics.table.format_table1`: ratios in percent, MOTP in px), the
sequence in place of the method and the pipeline's frames per second."""


def add_frame_options(parser: argparse.ArgumentParser) -> None:
    """Add the video pipeline's options to ``torchtrack track``."""
    g = parser.add_argument_group("frames (the video pipeline: registration → detector → tracker)")
    src = g.add_mutually_exclusive_group()
    src.add_argument("--video", type=Path, metavar="FILE", help="track the objects of a video file")
    src.add_argument("--frames", type=Path, metavar="DIR", help="track a folder of images (natural order)")
    src.add_argument("--sequences", type=Path, metavar="DIR",
                     help="evaluate every sequence folder in DIR and aggregate (shards over torchrun ranks)")
    # --compare and --trackers of torchtrack track also apply to --sequences: the detector runs once per
    # sequence and every tracker runs on its detections.
    g.add_argument("--pipeline-config", type=config_file(*PIPELINE_PRESETS), metavar="YAML", default=None,
                   help="pipeline settings (configs/pipeline.yaml); default: the embedded ones, which write "
                        "tracks.txt 3 frames behind the video (fixed-lag output); configs/pipeline-online.yaml "
                        "writes each frame at once; configs/pipeline-fewer-switches.yaml trades a point of MOTA "
                        "for about a fifth fewer identity switches (4 frames behind)")
    g.add_argument("--weights", type=Path, metavar="PT", default=None,
                   help="detector weights (default: the shipped ones)")
    g.add_argument("--camera", type=Path, metavar="JSON", default=None,
                   help="true camera motion (camera.json of a synthetic sequence) to measure registration")
    g.add_argument("--truth-csv", type=Path, metavar="CSV", default=None,
                   help="score against a WPAFB truth CSV (transformed_object_states.csv) as --score says "
                        "(default: the paper's protocol, moving vehicles are targets, the others don't-care); "
                        "frame 1 of the CSV is the first frame; CSV frames beyond the video are not scored")
    g.add_argument("--no-video", action="store_true", help="do not write annotated.mp4")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")


def _score_row(name: str, m: dict | None, fps: float) -> list:
    if m is None:
        return [name, *["-"] * (len(HEADER) - 2), fps]
    return table1_row(name, {**m, "FPS": fps})


def frame_inputs_given(args: argparse.Namespace) -> bool:
    """Whether ``--video``, ``--frames`` or ``--sequences`` was given."""
    return bool(args.video or args.frames or args.sequences)


def pipeline_config(args: argparse.Namespace, tracker_options: dict | None) -> PipelineConfig:
    """``--pipeline-config`` (default: the embedded settings) with ``--tracker``, ``--config``'s options for
    it, ``--threads``, ``--device``, ``--weights`` and ``--no-video``."""
    config = load_pipeline_config(args.pipeline_config)
    changes = {"tracker": args.tracker, "threads": args.threads, "device": args.device}
    if tracker_options:
        changes["tracker_options"] = tracker_options
    if args.weights:
        changes["detector_weights"] = str(args.weights)
    if args.no_video:
        changes["video"] = False
    return config.replace(**changes)


def run_frame_inputs(args: argparse.Namespace, command: str, tracker_options: dict | None = None,
                     inputs: list[Path | None] = ()) -> int:
    """Run the pipeline for ``--video``/``--frames``/``--sequences`` and print its scores; ``command`` is
    the one named in the output folder's marker, ``inputs`` the paths it reads (kept out of it)."""
    if args.detections:
        raise TorchtrackError("give either --detections or one of --video/--frames/--sequences, not both")
    config = pipeline_config(args, tracker_options)
    out = args.out
    if args.sequences:
        if args.gt:
            raise TorchtrackError("--gt does not apply to --sequences: each sequence folder holds its gt.txt")
        compare = (args.trackers or tracker_names()) if args.compare else []
        try:
            with shared_output(out, command, args.force, inputs) as staging:
                summary = run_sequences(args.sequences, staging, config, progress=not args.no_progress,
                                        compare=compare, score=args.score)
        finally:
            destroy()
        if summary is None:  # a torchrun rank other than 0
            return 0
        rows = [_score_row(n, m.get("clear_mot"), m["fps"]["end_to_end"]) for n, m in summary["sequences"].items()]
        if "aggregate" in summary:
            rows.append(_score_row("ALL", summary["aggregate"], summary["fps_per_process"]))
        print(protocol(args.score == "moving", config.threshold))
        print(format_table(HEADER, rows, floatfmt=".2f"))
        print(f"{len(summary['sequences'])} sequences, {summary['frames']} frames, tracker {config.tracker}, "
              f"{summary['world_size']} process(es); wrote {out}/metrics.json and {out}/<sequence>/")
        if "trackers" in summary:
            print(f"all trackers on the same detections, pooled over {summary['aggregate']['sequences']} sequences "
                  "(FPS: the tracker alone):")
            print(format_table1(summary["trackers"], protocol(args.score == "moving", config.threshold)))
        if "registration_error_px" in summary:
            print("registration error vs camera truth: median of sequence medians "
                  f"{summary['registration_error_px']['median_of_sequence_medians']:.3f} px")
        write_json(args.json, summary)
        return 0
    if args.gt and args.truth_csv:
        raise TorchtrackError("give either --gt or --truth-csv, not both")
    if args.strips:
        m, files = _run_strips(args, config, command, inputs)
        if m is None:  # a torchrun rank other than 0
            return 0
    else:
        source = open_frames(args.video or args.frames)
        gt, ignore = _truth(args, len(source))
        calibrate = getattr(args, "calibrate", None)
        result = track(frames=args.frames, video=args.video, calibrate=calibrate, seed=args.seed,
                       tracker=config.tracker, gt=gt, ignore=ignore, gt_name=str(args.truth_csv or args.gt),
                       score=args.score, device=args.device, pipeline_config=config, camera=_camera(args), out=out,
                       force=args.force, inputs=inputs, progress=not args.no_progress)
        if result.calibration is not None:
            print_calibration(result.calibration)
        m, files = result.report, result.files
    name = Path(args.video or args.frames).name
    gt_given = bool(args.gt or args.truth_csv)
    print(protocol(args.score == "moving", config.threshold) if gt_given else "not scored (no truth given)")
    print(format_table(HEADER, [_score_row(name, m.get("clear_mot"), m["fps"]["end_to_end"])], floatfmt=".2f"))
    timings = ", ".join(f"{k} {v:.2f}s" for k, v in m["timings_s"].items())
    print(f"{m['frames']} frames, tracker {config.tracker}: {timings}")
    reg = m["registration"]
    if reg["residual_px"] and reg["gate_pass_fraction"]:
        print(f"registration: frame-to-frame residual median {reg['residual_px']['median']:.3f} px "
              f"(max {reg['residual_px']['max']:.3f}), {reg['segments']} segment(s); the gate passes at most "
              f"{100 * reg['gate_pass_fraction']['max']:.1f} % of a frame's pixels (median "
              f"{100 * reg['gate_pass_fraction']['median']:.1f} %)")
    if "registration_error_px" in m:
        print(f"registration error vs camera truth: median {m['registration_error_px']['median']:.3f} px")
    print("wrote " + ", ".join(str(p) for p in files.values()))
    write_json(args.json, m)
    return 0


def _truth(args: argparse.Namespace, frames: int) -> tuple[MOTData | None, np.ndarray | None]:
    """``--gt`` or ``--truth-csv`` for a video of ``frames`` frames, with its don't-care lines under ``--score``
    (:func:`torchtrack.io.moving.dont_care`)."""
    if args.truth_csv:
        gt, not_moving = wpafb_truth(args.truth_csv, frames)
        return gt, not_moving if args.score == "moving" else None
    if not args.gt:
        return None, None
    gt = read_mot(args.gt)
    return gt, dont_care(gt, args.score, flags_beside(args.gt))


def _camera(args: argparse.Namespace) -> np.ndarray | None:
    return read_camera(args.camera) if args.camera else None


def _run_strips(args: argparse.Namespace, config: PipelineConfig, command: str, inputs: list[Path | None]
                ) -> tuple[dict | None, dict[str, Path]]:
    """``--strips``: the pipeline over the strips of the torchrun ranks; rank 0 writes the folder and gets the
    metrics and the files' final paths, the other ranks ``(None, {})``."""
    folder = OutputFolder(args.out, command, args.force, inputs=inputs)
    with strip_group() as rank, \
            (folder if rank == 0 else rank_output(rank, args.out, command, args.force, inputs)) as staging:
        source = open_frames(args.video or args.frames)
        gt, ignore = _truth(args, len(source)) if rank == 0 else (None, None)
        built = {}
        built["detector"], built["tracker"] = frame_strips(config, source.shape[0], args)
        config = config if rank == 0 else config.replace(video=False)
        result = track_video(source, staging, config, gt=gt, gt_path=str(args.truth_csv or args.gt), ignore=ignore,
                             camera=_camera(args), progress=not args.no_progress and rank == 0, **built)
        result.metrics.update(strip_metrics(built["tracker"]))
        write_json(result.files["metrics"], result.metrics)
    if rank != 0:
        return None, {}
    return result.metrics, {kind: folder.final(path) for kind, path in result.files.items()}
