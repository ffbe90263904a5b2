"""What a tracker is given per frame: :class:`FrameDetections`, from the video pipeline's detector
(:class:`torchtrack.pipeline.detection.Detection`) or from a MOTChallenge detection file (:func:`mot_frames`)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import NamedTuple

import numpy as np
import torch

from torchtrack.io.mot import MOTData


class FrameDetections(NamedTuple):
    """Detections of one frame: ``positions``/``velocities (K, 2)`` in reference coordinates, ``scores (K,)``,
    ``homography (3, 3)`` frame → reference; ``image_positions``/``image_velocities`` in frame coordinates
    (the detector's output); ``motion (K,)`` the motion evidence at each detection
    (:func:`~torchtrack.pipeline.detection.motion_evidence`); ``strong (K,)`` whether it scored at least the
    detection threshold (the others are weak detections, decoded further down for
    :class:`~torchtrack.pipeline.tracker_stream.TrackerStream` to continue tracks); ``tones (K,)`` the grey
    level at each detection (:func:`~torchtrack.pipeline.detection.grey_level`; None where not measured);
    ``clutter (K,)`` the frame difference the registration's residual leaves at each detection (grey levels,
    :func:`~torchtrack.pipeline.detection.misregistration`; None: not measured); ``segment`` the registration's
    segment (a frame it could not register starts the next, and the tracks restart there); ``cluttered`` whether
    the moving-object gate was raised on this frame (its plain form passed more than its budget of the pixels);
    ``noise`` the frame difference's noise level (:func:`~torchtrack.pipeline.detection.frame_noise`; 0: not
    measured).
    On the first frame there is no previous frame: ``velocities`` are NaN (unknown) and ``motion`` is ``inf``,
    so that the moving-object gate passes everything and the trackers start without a velocity."""

    index: int
    homography: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    scores: np.ndarray
    image_positions: np.ndarray
    image_velocities: np.ndarray
    motion: np.ndarray
    strong: np.ndarray
    tones: np.ndarray | None = None
    clutter: np.ndarray | None = None
    segment: int = 0
    cluttered: bool = False
    noise: float = 0.0

    @classmethod
    def registered(cls, index: int, positions: np.ndarray, velocities: np.ndarray | None = None,
                   scores: np.ndarray | None = None) -> FrameDetections:
        """Detections already in one coordinate frame (a detection file, a tuning window): identity
        homography, every one strong, ``velocities (K, 2)`` NaN where not given, ``scores`` 1 where not
        given, motion evidence ``inf`` (no frames to measure it: a ``min_motion`` gate passes everything)."""
        pos = np.asarray(positions, np.float64).reshape(-1, 2)
        vel = np.full_like(pos, np.nan) if velocities is None else np.asarray(velocities, np.float64).reshape(-1, 2)
        k = len(pos)
        scores = np.ones(k) if scores is None else np.asarray(scores, np.float64)
        return cls(int(index), np.eye(3), pos, vel, scores, pos, vel, np.full(k, np.inf), np.ones(k, bool))

    def select(self, keep: np.ndarray) -> FrameDetections:
        """The detections where ``keep (K,)`` (a mask or indices)."""
        return self._replace(**{k: v[keep] for k, v in self._asdict().items()
                                if k not in ("index", "homography", "segment", "cluttered", "noise") and v is not None})

    def moving(self, min_speed: float = 0.0, min_motion: float = 0.0, margin: float = 0.0,
               noise_factor: float = 0.0) -> FrameDetections:
        """The detections with predicted speed ``>= min_speed`` px/frame (or unknown) and motion evidence
        ``>= max(min_motion, noise_factor · noise) + gate_margin(margin · clutter)`` (``min_motion`` 0: the motion
        gate off, its noise part too)."""
        need = motion_threshold(min_motion, noise_factor, self.noise) + (
            gate_margin(margin * self.clutter) if margin and self.clutter is not None else 0.0)
        return self.select(~(np.hypot(self.velocities[:, 0], self.velocities[:, 1]) < min_speed)
                           & (self.motion >= need))


def motion_threshold(min_motion: float, noise_factor: float, noise: float) -> float:
    """The moving-object gate's plain threshold on a frame whose difference has noise level ``noise`` (grey
    levels): ``max(min_motion, noise_factor · noise)``; 0 where ``min_motion`` is 0 (the gate off, its noise part
    too)."""
    return max(min_motion, noise_factor * noise) if min_motion > 0 else 0.0


MOTION_STEP = 1.0
"""Grey levels: the motion evidence is an 8-bit box-filter mean, rounded to whole grey levels, so a
misregistration difference below one level is not told apart from that rounding (:func:`gate_margin`)."""


def gate_margin(difference: np.ndarray | float) -> np.ndarray | float:
    """What the moving-object gate adds to ``min_motion`` for a registration ``difference`` (grey levels) at a
    point: the part beyond :data:`MOTION_STEP`. A detection at exactly ``min_motion`` is then not refused for a
    tenth of a grey level the residual's measurement noise leaves on a vehicle's own edges."""
    return np.maximum(np.asarray(difference, np.float64) - MOTION_STEP, 0.0)


def as_numpy(x, shape_tail: tuple[int, ...]) -> np.ndarray:
    """``x`` (tensor, array, sequence or None) as a float64 array of shape ``(-1, *shape_tail)``."""
    if x is None:
        return np.zeros((0, *shape_tail))
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, np.float64).reshape(-1, *shape_tail)


def mot_frames(det: MOTData, frames: Sequence[int]) -> Iterator[FrameDetections]:
    """The detections ``det`` of every frame in ``frames`` (frames without detections give ``K = 0``) as
    :meth:`FrameDetections.registered`, with the file's scores and velocities (columns 8–9, where given)."""
    for f, idx in zip(frames, det.split(frames)):
        one = det.select(idx)
        yield FrameDetections.registered(f, one.centers(), one.velocity(), one.conf)


MAX_GAP = 50
"""Longest run of frames without data that a stream steps through one frame at a time (:func:`stream_frames`)."""


def stream_frames(*datas: MOTData | None, max_gap: int = MAX_GAP) -> np.ndarray:
    """The frame numbers a stream steps through: every frame from the first to the last present in any of
    ``datas`` (frames between them without detections are frames in which nothing was detected), except that
    a gap of more than ``max_gap`` frames without data is crossed in one step — the trackers predict by the
    frame difference — so that sparse frame numbers (frames 1 and 10⁹) cost nothing. Sorted int64 array."""
    frames = [d.frame for d in datas if d is not None and d.size]
    if not frames:
        return np.zeros(0, dtype=np.int64)
    present = np.unique(np.concatenate(frames))
    gaps = np.diff(present)
    short = np.flatnonzero((gaps > 1) & (gaps <= max_gap + 1))
    filled = [np.arange(present[i] + 1, present[i + 1]) for i in short]
    return np.unique(np.concatenate([present, *filled])) if filled else present
