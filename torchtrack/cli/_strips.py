"""``torchtrack track --strips``: a detection file tracked over horizontal strips, one per ``torchrun`` rank
(:mod:`torchtrack.pipeline.strip_tracking`).

Every rank reads the whole file and runs the same stream with its strip's tracker; every rank gets the merged
tracks, and rank 0 alone writes the output folder and prints (the other ranks stage theirs in a temporary
folder that is removed). Under ``torchrun`` (``WORLD_SIZE`` set) the gloo process group is started here and
destroyed at the end; without it the run is one strip, the plain tracker with its identities renumbered.
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

from torchtrack.errors import TorchtrackError
from torchtrack.filters.multitarget import Tracker
from torchtrack.io.mot import MOTData
from torchtrack.io.outputs import OutputFolder
from torchtrack.pipeline.strip_tracking import BAND, StripConfig, StripTracker


def add_strip_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--strips", action="store_true",
                        help="track over horizontal strips, one per torchrun rank (gloo): each rank tracks the "
                             "detections of its strip widened by --band px, identities are handed over at the "
                             "seams, rank 0 writes the outputs (with --detections; docs/scale.md)")
    parser.add_argument("--band", type=float, default=BAND, metavar="PX",
                        help=f"--strips: handover band in px each side of a strip (default {BAND:g})")
    parser.add_argument("--strip-height", type=int, default=None, metavar="ROWS",
                        help="--strips: rows 0..ROWS split into equal strips (default: past the detections' "
                             "largest y)")


def check_strip_arguments(args: argparse.Namespace, frame_inputs: bool) -> None:
    """The argument errors of ``--strips`` (before anything is read or written)."""
    if not args.strips:
        return
    if args.detections is None or args.compare or args.benchmark is not None or frame_inputs:
        raise TorchtrackError("--strips runs one tracker on --detections (not with --compare, --benchmark, "
                              "--video, --frames or --sequences)")
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


@contextmanager
def rank_output(rank: int, out: Path, command: str, force: bool, inputs: list) -> Iterator[Path]:
    """The staging folder of rank 0's output folder; a temporary folder, removed, on the other ranks."""
    if rank == 0:
        with OutputFolder(out, command, force, inputs=inputs) as staging:
            yield staging
    else:
        with tempfile.TemporaryDirectory(prefix=f"torchtrack-strips-rank{rank}-") as staging:
            yield Path(staging)
