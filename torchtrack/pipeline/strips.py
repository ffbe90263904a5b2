"""Detection of a frame stream over horizontal strips, one strip per rank of a process group (under
``torchrun``, ``torch.distributed``).

Rank ``r`` of ``W`` detects the strip ``strip_rows(H, W)[r]`` of every frame (every rank reads the whole frame:
the strip's network window reaches ``HALO`` px past its rows, and velocities are refined on the whole frames),
with the whole previous frame's detections as the detector's prior. Each frame the strips' detections are
all-gathered, so that every rank holds the whole frame's detections — the next frame's prior — in the whole-frame
decoding's order (:func:`merge_strips`). The result equals one process's loop of
:meth:`torchtrack.detector.Detector.detect` over the frames (up to float rounding), as long as no strip reaches
its peak cap (``peaks_for`` of its area). :class:`StripDetector` is the same per frame behind the detector's
``detect`` interface, for the video pipeline (``torchtrack track --frames DIR --strips``), which registers the
whole frames on every rank and hands it the prior itself.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence

import numpy as np
import torch
import torch.distributed as dist

from torchtrack.detector import Detections, Detector
from torchtrack.detector.network import MULTIPLE
from torchtrack.errors import TorchtrackError


def strip_rows(height: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` strips ``(y0, y1)`` that partition the rows ``0`` to ``height`` of a frame, as equal as the
    boundaries allow: multiples of 16 (the network's stride), the last strip ending at ``height``."""
    cells = -(-height // MULTIPLE)
    if not 1 <= parts <= cells:
        raise TorchtrackError(f"strips: {parts} strips of a {height}-row frame (1 to {cells}: "
                              f"each strip needs at least {MULTIPLE} rows)")
    bounds = [min(height, MULTIPLE * (cells * i // parts)) for i in range(parts + 1)]
    return list(zip(bounds[:-1], bounds[1:]))


def merge_strips(parts: Sequence[Detections]) -> Detections:
    """The detections of strips ``parts`` (top to bottom, each best score first) as one frame's: best score
    first, equal scores top strip first — the order of the whole frame's decoding (equal scores in raster order
    of their cells)."""
    xy, score, velocity = (torch.cat([torch.as_tensor(getattr(p, f)) for p in parts]).float()
                           for f in ("xy", "score", "velocity"))
    order = torch.argsort(-score.double(), stable=True)
    return Detections(xy[order], score[order], velocity[order], torch.ones(len(order), dtype=torch.bool))


def rank_and_size(group: dist.ProcessGroup | None) -> tuple[int, int]:
    """This process's rank in ``group`` and the group's size; ``(0, 1)`` without an initialised process group."""
    if not (dist.is_available() and dist.is_initialized()):
        return 0, 1
    return dist.get_rank(group), dist.get_world_size(group)


class StripDetector:
    """A :class:`Detector` over the strips of the ranks of ``group`` (default: the default process group; none
    initialised: this process alone, the whole frame), with the detector's ``detect`` interface: every rank
    calls ``detect`` with the same whole frames and prior and gets the whole frame's detections, its own strip
    detected and the others all-gathered (:func:`merge_strips`). The video pipeline's
    :class:`~torchtrack.pipeline.detection.Detection` takes it in place of the detector."""

    def __init__(self, detector: Detector, group: dist.ProcessGroup | None = None):
        self.detector, self.group = detector, group
        self.rank, self.world = rank_and_size(group)

    @property
    def config(self):
        """The detector's configuration (its decoding threshold is the pipeline's prior threshold)."""
        return self.detector.config

    def detect(self, frame, prev_frame=None, prev_points=None, threshold: float | None = None,
               prev_velocity=None) -> Detections:
        """:meth:`Detector.detect` of the whole frame, computed over the strips."""
        if self.world == 1:
            return self.detector.detect(frame, prev_frame, prev_points, threshold, prev_velocity)
        rows = strip_rows(frame.shape[0], self.world)[self.rank]
        mine = self.detector.detect(frame, prev_frame, prev_points, threshold, prev_velocity, rows=rows)
        parts: list = [None] * self.world
        dist.all_gather_object(parts, mine, group=self.group)
        return merge_strips(parts)


def detect_strips(detector: Detector, frames: Iterable[np.ndarray | torch.Tensor],
                  group: dist.ProcessGroup | None = None) -> Iterator[Detections]:
    """The detections of each frame ``(H, W)`` of ``frames`` (module docstring), on every rank of ``group``
    (default: the default process group; none initialised: this process alone, the whole frame).

    Frame ``k`` is detected with ``prev_frame`` frame ``k - 1`` and the prior (points and velocities) of frame
    ``k - 1``'s whole detections; frame 0 with neither, as :meth:`Detector.detect` alone. Every rank must
    iterate the same frames."""
    strips = StripDetector(detector, group)
    prev_frame = prior = prior_velocity = None
    for frame in frames:
        found = strips.detect(frame, prev_frame, prior, prev_velocity=prior_velocity)
        yield found
        prev_frame, prior, prior_velocity = frame, found.xy, found.velocity
