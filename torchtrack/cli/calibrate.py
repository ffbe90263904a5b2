"""``torchtrack calibrate``: fit the sensor and the dynamics from detections alone (no truth)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

NAME = "calibrate"
HELP = "fit a new sensor (noise, p_D, clutter, velocity noise) and the tracker's decisions from detections alone"
DESCRIPTION = """Calibrate the trackers to a new sensor from its detections alone, without truth
(docs/calibrate.md): the enhanced GM-PHD tracks the frames, its tracks are smoothed, and the position noise,
detection probability and velocity noise maximise the multi-object likelihood of the detections given them;
the clutter density and velocity spread are measured where no track passes; the process noise, survival and
birth rate come from the tracks. The tracker's birth weight, coasting and confirmation are then chosen by the
MOTA of a parametric bootstrap under the fitted model.

Writes DIR/track.yaml (a torchtrack track --config file with gmphd, labelled-gmphd, glmb and pmb sections),
DIR/calibration.json (fitted values with standard errors, the likelihood before and after, frames used,
seconds, the decisions and the bootstrap's scores) and DIR/loss.png, as one set. Progress on stderr.

example:
  torchtrack calibrate --detections out/wpafb/det.txt --frames 1 400 --out out/calibrate
  torchtrack track --detections out/wpafb/det.txt --config out/calibrate/track.yaml --out out/track
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from torchtrack.cli._common import add_common_options, add_force_option, positive_int
    from torchtrack.filters.trackers.protocol import tracker_names

    parser.add_argument("--detections", type=Path, required=True, metavar="DET",
                        help="detections, MOTChallenge text (velocities in columns 8-9 where present)")
    parser.add_argument("--tracker", choices=tracker_names(), default="gmphd",
                        help="the tracker whose section the summary prints (track.yaml holds gmphd, "
                             "labelled-gmphd, glmb and pmb)")
    parser.add_argument("--frames", type=positive_int, nargs=2, default=None, metavar=("A", "B"),
                        help="calibrate on frames A-B inclusive (default: all)")
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
    det = read_mot(args.detections)
    velocity = {"auto": None, "yes": True, "no": False}[args.velocity]
    with OutputFolder(args.out, "torchtrack calibrate", args.force, inputs=[args.detections]) as staging:
        result = calibrate_into(det, Path(staging), args.frames, velocity, args.seed, str(args.detections))
    record = result.record(str(args.detections))
    write_json(args.json, record)
    c = result.calibration
    for key, value in c.values.items():
        err = c.stderr.get(key)
        print(f"{key:24s} {value:.4g}" + (f" ± {err:.2g}" if err is not None else ""))
    if args.tracker in result.sections:
        print(f"{args.tracker}: {result.sections[args.tracker]}")
    print(f"wrote {args.out}/track.yaml, calibration.json, loss.png ({result.seconds:.1f} s)")
    return 0


def calibrate_into(det, folder: Path, frames, velocity, seed: int, source: str):
    """Calibrate on ``det`` and write track.yaml, calibration.json and loss.png into ``folder``."""
    from torchtrack.io.outputs import write_json, write_yaml
    from torchtrack.tuning.calibration import calibrate, plot_calibration

    result = calibrate(det, tuple(frames) if frames else None, velocity, seed, source,
                       progress=lambda line: print(f"calibrate: {line}", file=sys.stderr))
    c = result.calibration
    write_yaml(folder / "track.yaml", result.sections,
               header=f"# torchtrack calibrate on {source}, frames {c.frames[0]}-{c.frames[1]}\n")
    write_json(folder / "calibration.json", result.record(source))
    plot_calibration(result, folder / "loss.png")
    return result
