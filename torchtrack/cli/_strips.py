"""``torchtrack track --strips``: a detection file or a frame stream tracked over horizontal strips, one per
``torchrun`` rank (:mod:`torchtrack.pipeline.strip_tracking`).

With ``--detections`` every rank reads the whole file and runs the same stream with its strip's tracker. With
``--frames``/``--video`` every rank reads and registers every whole frame, detects its strip of the frame's rows
and gets the whole frame's detections (:class:`~torchtrack.pipeline.strips.StripDetector`), then runs the same
tracker stream with its strip's tracker (the strips in reference coordinates, :func:`frame_strips`). Every rank
gets the merged tracks, and rank 0 alone writes the output folder (the annotated video too) and prints (the
other ranks stage theirs in a temporary folder that is removed). Under ``torchrun`` (``WORLD_SIZE`` set) the
gloo process group is started here and destroyed at the end; without it the run is one strip, the plain
tracker with its identities renumbered.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch.distributed as dist

from torchtrack.detector import load_detector
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import Tracker, make_tracker
from torchtrack.io.mot import MOTData
from torchtrack.io.outputs import OutputFolder
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.strip_tracking import BAND, StripConfig, StripTracker
from torchtrack.pipeline.strips import StripDetector


def add_strip_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--strips", action="store_true",
                        help="track over horizontal strips, one per torchrun rank (gloo): each rank tracks the "
                             "detections of its strip widened by --band px, identities are handed over at the "
                             "seams, rank 0 writes the outputs (with --detections, --frames or --video; with "
                             "frames each rank detects its strip of every frame; docs/scale.md)")
    parser.add_argument("--band", type=float, default=BAND, metavar="PX",
                        help=f"--strips: handover band in px each side of a strip (default {BAND:g})")
    parser.add_argument("--strip-height", type=int, default=None, metavar="ROWS",
                        help="--strips: the tracker's rows 0..ROWS split into equal strips (default: past the "
                             "detections' largest y; with frames, the frame's height)")


def check_strip_arguments(args: argparse.Namespace, frame_inputs: bool) -> None:
    """The argument errors of ``--strips`` (before anything is read or written)."""
    if not args.strips:
        return
    if args.compare or args.benchmark is not None or args.sequences or not (args.detections or frame_inputs):
        raise TorchtrackError("--strips runs one tracker on --detections, --frames or --video (not with --compare, "
                              "--benchmark or --sequences)")
    if not (math.isfinite(args.band) and args.band >= 0):
        raise TorchtrackError(f"--band must be a distance >= 0 px, got {args.band:g}")
    if args.strip_height is not None and args.strip_height < 1:
        raise TorchtrackError(f"--strip-height must be a positive number of rows, got {args.strip_height}")


@contextmanager
def strip_group() -> Iterator[int]:
    """This process's rank, the gloo process group started under ``torchrun`` for the block (0 without)."""
    if "WORLD_SIZE" not in os.environ or dist.is_initialized():
        yield dist.get_rank() if dist.is_initialized() else 0
        return
    dist.init_process_group("gloo")
    try:
        yield dist.get_rank()
    finally:
        dist.destroy_process_group()


def strip_tracker(tracker: Tracker, det: MOTData, args: argparse.Namespace) -> StripTracker:
    """``tracker`` over the strips of ``--strip-height`` rows (default: the rows up to past the detections'
    largest centre y, what the trackers are given), ``--band``."""
    height = args.strip_height
    if height is None:
        height = int(math.floor(float(det.centers()[:, 1].max()))) + 1 if det.size else 1
    return StripTracker(tracker, StripConfig(height, band=args.band))


def strip_metrics(tracker: StripTracker) -> dict:
    """What ``metrics.json`` adds with ``--strips``: the ranks, the band, the tracker's rows and this rank's cap
    hits."""
    return {"strips": tracker.world, "band": tracker.config.band, "strip_height": tracker.config.height,
            "cap_hits": tracker.cap_hits}


@contextmanager
def rank_output(rank: int, out: Path, command: str, force: bool, inputs: list) -> Iterator[Path]:
    """The staging folder of rank 0's output folder; a temporary folder, removed, on the other ranks."""
    if rank == 0:
        with OutputFolder(out, command, force, inputs=inputs) as staging:
            yield staging
    else:
        with tempfile.TemporaryDirectory(prefix=f"torchtrack-strips-rank{rank}-") as staging:
            yield Path(staging)


def frame_strips(config: PipelineConfig, height: int, args: argparse.Namespace) -> tuple[StripDetector, StripTracker]:
    """The detector and tracker of ``--frames``/``--video`` with ``--strips``: ``config``'s detector over the
    strips of the frame's ``height`` rows, and its tracker over the strips of ``--strip-height`` rows (default:
    ``height``) widened by ``--band``.

    The tracker works in reference coordinates (the first frame's, :mod:`torchtrack.pipeline.track_video`), so
    its seams are rows of the first frame: a vehicle's owner changes only when the vehicle itself crosses a
    seam, not when the camera moves (at the first frame the tracker's and the detector's seams coincide). As the
    camera drifts, a seam moves in the image and may leave it (the outer strips reach past the frame, so every
    position keeps an owner): the ranks' shares of the tracking then differ, not the result."""
    detector = StripDetector(load_detector(config.detector_weights, config.detector_tile, config.detector_backend))
    tracker = make_tracker(config.tracker, config.options_for(config.tracker))
    return detector, StripTracker(tracker, StripConfig(args.strip_height or height, band=args.band))
