"""``torchtrack calibrate``: fit the sensor and the dynamics from detections alone (no truth)."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "calibrate"
HELP = "fit a new sensor (noise, p_D, clutter, velocity noise) and the trackers' options without truth"
DESCRIPTION = """Calibrate the trackers to a new sensor or camera without truth, from its detections or its frames
(docs/calibrate.md): the enhanced GM-PHD tracks the frames, its tracks are smoothed, and the position noise,
detection probability and velocity noise maximise the multi-object likelihood of the detections given them;
the clutter density and velocity spread are measured where no track passes; the process noise, survival and
birth rate come from the tracks. The tracker's birth weight, coasting and confirmation are then chosen by the
MOTA of a parametric bootstrap under the fitted model, which then also moves the fitted values (sensor
noise, p_D, clutter density, process noise, velocity noise) and the extraction threshold where that tracks the
simulated frames better; each tracker keeps its built-in options unless its calibrated ones make clearly fewer
errors there. A fit that failed (the tracker following clutter: q or a noise at its bound, p_D far
below the share of frames with a detection, a bootstrap MOTA near zero, a tracker that reports nothing) is
refitted from a stricter start and, if that fails too, track.yaml holds the built-in options; the status line
and calibration.json's "status" (ok, retried, defaults) say which.

With --from-frames (a folder of images or a video) the video pipeline runs on the frames and the detections
its tracker is given (moving, in the first frame's coordinates, with velocities) are calibrated on.

Writes DIR/track.yaml (a torchtrack track --config file with gmphd, labelled-gmphd, glmb and pmb sections),
DIR/calibration.json (status, fitted values with standard errors, the likelihood before and after, frames
used, seconds, the decisions and the bootstrap's scores) and DIR/loss.png, as one set. Progress on stderr.

examples:
  torchtrack calibrate --detections out/wpafb/det.txt --frames 1 400 --out out/calibrate
  torchtrack track --detections out/wpafb/det.txt --config out/calibrate/track.yaml --out out/track
  torchtrack calibrate --from-frames out/cam/frames --frames 1 20 --out out/calibrate-cam
  torchtrack track --frames out/cam/frames --calibrate 20 --out out/track-cam     # both at once
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from torchtrack.cli._common import PIPELINE_PRESETS, add_common_options, add_force_option, config_file, positive_int
    from torchtrack.filters.trackers.protocol import tracker_names

    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--detections", type=Path, metavar="DET",
                        help="detections, MOTChallenge text (velocities in columns 8-9 where present)")
    source.add_argument("--from-frames", type=Path, metavar="PATH",
                        help="a folder of images or a video: the video pipeline (registration, detector, "
                             "moving-object gate) runs on them and its tracker's input is calibrated on; "
                             "track.yaml then goes to torchtrack track --frames/--video --config")
    parser.add_argument("--pipeline-config", type=config_file(*PIPELINE_PRESETS), metavar="YAML", default=None,
                        help="with --from-frames: the pipeline's settings (default: the embedded ones)")
    parser.add_argument("--weights", type=Path, metavar="PT", default=None,
                        help="with --from-frames: detector weights (default: the shipped ones)")
    parser.add_argument("--tracker", choices=tracker_names(), default="gmphd",
                        help="the tracker whose section the summary prints (track.yaml holds gmphd, "
                             "labelled-gmphd, glmb and pmb)")
    parser.add_argument("--frames", type=positive_int, nargs=2, default=None, metavar=("A", "B"),
                        help="calibrate on frames A-B inclusive (default: all; with --from-frames the pipeline "
                             "runs frames 1-B, and frame 1, without velocities, is left out)")
    parser.add_argument("--velocity", choices=("auto", "yes", "no"), default="auto",
                        help="fit the velocity noise: yes needs velocities in the file, no ignores them "
                             "(default auto: where present)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    add_force_option(parser)
    add_common_options(parser)


def run(args: argparse.Namespace) -> int:
    from torchtrack.errors import TorchtrackError
    from torchtrack.io.mot import read_mot
    from torchtrack.io.outputs import OutputFolder, write_json

    if args.frames is not None and args.frames[0] > args.frames[1]:
        raise TorchtrackError(f"--frames: A must not exceed B; got {args.frames[0]} {args.frames[1]}")
    if args.detections is None and args.velocity == "no":
        raise TorchtrackError("--velocity no: the pipeline's detections always carry velocities")
    given = args.detections or args.from_frames
    velocity = {"auto": None, "yes": True, "no": False}[args.velocity]
    with OutputFolder(args.out, "torchtrack calibrate", args.force, inputs=[given]) as staging:
        if args.detections is not None:
            result = calibrate_into(read_mot(args.detections), Path(staging), args.frames, velocity, args.seed,
                                    str(args.detections))
        else:
            result = _calibrate_frames(args, Path(staging))
    write_json(args.json, result.record(str(given)))
    c = result.calibration
    for key, value in (c.values if c is not None else {}).items():
        err = c.stderr.get(key)
        print(f"{key:24s} {value:.4g}" + (f" ± {err:.2g}" if err is not None else ""))
    if args.tracker in result.sections:
        print(f"{args.tracker}: {result.sections[args.tracker]}")
    print(f"status: {result.status}: {result.message}" + "".join(f"; warning: {w}" for w in result.warnings))
    print(f"wrote {args.out}/track.yaml, calibration.json, loss.png ({result.seconds:.1f} s)")
    return 0


def _calibrate_frames(args: argparse.Namespace, folder: Path):
    """``--from-frames``: the pipeline's detections of frames 1-B, calibrated on frames A-B."""
    from torchtrack.calibrated_track import progress_line
    from torchtrack.io.frames import open_frames
    from torchtrack.pipeline.config import load_pipeline_config
    from torchtrack.tuning.video import calibrate_frames

    config = load_pipeline_config(args.pipeline_config)
    if args.weights is not None:
        config = config.replace(detector_weights=str(args.weights))
    source = open_frames(args.from_frames)
    first, last = args.frames if args.frames is not None else (1, len(source))
    result = calibrate_frames(source, config, last, args.seed, progress_line, first)
    result.write(folder, str(args.from_frames))
    return result


def calibrate_into(det, folder: Path, frames, velocity, seed: int, source: str):
    """Calibrate on ``det`` and write track.yaml, calibration.json and loss.png into ``folder``."""
    from torchtrack.calibrated_track import progress_line
    from torchtrack.tuning.calibration import calibrate

    result = calibrate(det, tuple(frames) if frames else None, velocity, seed, source, progress=progress_line)
    result.write(folder, source)
    return result
