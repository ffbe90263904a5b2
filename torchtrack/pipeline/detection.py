"""Steps 1–2 of the video pipeline: registration and detection of a frame stream
(:class:`Detection`), with the per-detection cues the tracker stream uses: motion evidence and grey level."""

from __future__ import annotations

import inspect

import cv2
import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.geometry import apply_homography, homography_jacobian, warp_previous
from torchtrack.pipeline.frame_detections import FrameDetections, as_numpy
from torchtrack.pipeline.registration import Registration
from torchtrack.pipeline.timer import StageTimer

MOTION_WINDOW = 5
"""Side (px) of the window over which :func:`motion_evidence` averages the frame difference."""


def motion_evidence(image: np.ndarray, previous: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mean absolute grey-level difference between ``image`` and the ``previous`` frame registered onto it,
    over a ``MOTION_WINDOW``-px square at each of ``points (K, 2)`` (x, y): a classical change-detection cue
    (moving vehicles leave a difference of tens of grey levels, static structure only sensor noise and
    parallax). ``(K,)``."""
    return _banded(lambda a, b: cv2.blur(cv2.absdiff(a, b), (MOTION_WINDOW, MOTION_WINDOW)), (image, previous),
                   points, MOTION_WINDOW // 2)


TONE_WINDOW = 3
"""Side (px) of the window over which :func:`grey_level` averages the frame."""


def grey_level(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mean grey level of ``image`` over a ``TONE_WINDOW``-px square at each of ``points (K, 2)`` (x, y): the
    tone of the vehicle detected there, the attribute the GM-PHD's ``tone_sigma`` compares between frames.
    ``(K,)``."""
    return _banded(lambda a: cv2.blur(a, (TONE_WINDOW, TONE_WINDOW)), (image,), points, TONE_WINDOW // 2)


BAND_ROWS = 256
"""Rows of the frame filtered at once by :func:`_banded`."""


def _banded(op, images: tuple[np.ndarray, ...], points: np.ndarray, halo: int) -> np.ndarray:
    """``op(*images)`` at the pixels nearest ``points (K, 2)`` (x, y), clipped to the frame, as float64 ``(K,)``.

    ``op``, a uint8 filter that reaches ``halo`` rows (OpenCV's box filter: integer sums, the same wherever the
    rows start), runs on bands of :data:`BAND_ROWS` rows with ``halo`` rows of the frame either side, only
    where a point falls: the values of the whole frame's filter, with a band's memory instead of the frame's."""
    h, w = images[0].shape
    x = np.clip(np.rint(points[:, 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.rint(points[:, 1]).astype(np.int64), 0, h - 1)
    out = np.empty(len(points), np.float64)
    for y0 in np.unique(y // BAND_ROWS) * BAND_ROWS:
        mine = np.nonzero((y >= y0) & (y < y0 + BAND_ROWS))[0]
        top, bottom = max(0, y0 - halo), min(h, y0 + BAND_ROWS + halo)
        out[mine] = op(*(im[top:bottom] for im in images))[y[mine] - top, x[mine]]
    return out


class Detection:
    """Registration + detection of a frame stream (steps 1–2 of the module docstring).

    ``detector`` has ``detect(frame, prev_frame, prev_points)`` returning an object with ``xy (K, 2)``,
    ``score (K,)`` and ``velocity (K, 2)`` (:class:`torchtrack.detector.Detections`: frame pixel coordinates,
    velocities ``x_k − x_{k-1}`` in px/frame). A detector whose ``detect`` takes ``prev_velocity`` gets the
    previous detections' velocities too (its motion-continuity check). With ``threshold`` (our
    :class:`torchtrack.detector.Detector` only) it decodes down to that score, and with ``weak_threshold`` further
    down still: the detections between the two are marked weak (``FrameDetections.strong`` false). The prior
    heatmap of the next frame takes only the detections at or above the detector's own threshold, so that
    weak peaks do not feed themselves.
    """

    def __init__(self, detector, registration: Registration, timer: StageTimer,
                 threshold: float | None = None, weak_threshold: float | None = None) -> None:
        self.detector = detector
        self.registration = registration
        self.timer = timer
        if "threshold" not in inspect.signature(detector.detect).parameters:
            if threshold is not None:
                raise TorchtrackError("detection_threshold needs a detector whose detect() takes a threshold")
            weak_threshold = None  # a stand-in detector decodes at its own threshold only
        given = [t for t in (threshold, weak_threshold) if t is not None]
        self.decode_threshold = min(given) if given else None
        self.prior_threshold = detector.config.decode.threshold if given else -np.inf
        self.strong_threshold = self.prior_threshold if threshold is None else threshold
        self.prev_image: np.ndarray | None = None
        self.prev_h = np.eye(3)
        self.prior_ref = np.zeros((0, 2))  # prior points (reference coordinates) for the next frame
        self.prior_velocity: np.ndarray | None = None  # their velocities (px/frame), where they are detections
        self.takes_velocity = "prev_velocity" in inspect.signature(detector.detect).parameters

    def __call__(self, index: int, image: np.ndarray) -> FrameDetections:
        with self.timer("registration"):
            h = self.registration(image).homography
            h_inv = np.linalg.inv(h)
            # Previous frame resampled into the current frame: x_{k-1} = H_{k-1}^{-1} H_k x_k.
            prev = image if self.prev_image is None else warp_previous(
                self.prev_image, np.linalg.inv(self.prev_h) @ h, image.shape, fill=image)
            prior = apply_homography(self.prior_ref, h_inv)
        with self.timer("detection"):
            extra = {} if self.decode_threshold is None else {"threshold": self.decode_threshold}
            if self.takes_velocity and self.prior_velocity is not None:
                extra["prev_velocity"] = self.prior_velocity
            found = self.detector.detect(image, prev, prior, **extra)
        pos, vel, scores = as_numpy(found.xy, (2,)), as_numpy(found.velocity, (2,)), as_numpy(found.score, ())
        with self.timer("registration"):
            pos_ref = apply_homography(pos, h)
            vel_ref = (homography_jacobian(h, pos) @ vel[:, :, None])[:, :, 0] if len(pos) else vel
            if self.prev_image is None:
                vel_ref, motion = np.full_like(vel_ref, np.nan), np.full(len(pos), np.inf)
            else:
                motion = motion_evidence(image, prev, pos)
        self.prev_image, self.prev_h = image, h
        prior = scores >= self.prior_threshold
        self.prior_ref = pos_ref[prior]
        self.prior_velocity = None if np.isnan(vel_ref).any() else vel[prior]
        return FrameDetections(index, h, pos_ref, vel_ref, scores, pos, vel, motion, scores >= self.strong_threshold,
                               grey_level(image, pos))

    def set_prior(self, points: np.ndarray) -> None:
        """Use ``points (N, 2)`` (reference coordinates, without velocities) for the next frame's prior heatmap
        instead of this frame's detections (``prior: tracks``)."""
        self.prior_ref = np.asarray(points, np.float64).reshape(-1, 2)
        self.prior_velocity = None
