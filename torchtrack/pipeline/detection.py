"""Steps 1–2 of the video pipeline: registration and detection of a frame stream
(:class:`Detection`), with the per-detection cues the tracker stream uses: motion evidence and grey level."""

from __future__ import annotations

import inspect

import cv2
import numpy as np
from scipy.spatial import cKDTree

from torchtrack.errors import TorchtrackError
from torchtrack.geometry import apply_homography, homography_jacobian, warp_previous
from torchtrack.pipeline.frame_detections import FrameDetections, as_numpy, gate_margin, motion_threshold
from torchtrack.pipeline.registration import Registration, RegistrationResult
from torchtrack.pipeline.timer import StageTimer

MOTION_WINDOW = 5
"""Side (px) of the window over which :func:`motion_evidence` averages the frame difference."""

BAND_ROWS = 256
"""Rows of the frame filtered at once by :func:`_banded` and :func:`gate_pass_fraction`."""


def motion_evidence(image: np.ndarray, previous: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mean absolute grey-level difference between ``image`` and the ``previous`` frame registered onto it,
    over a ``MOTION_WINDOW``-px square at each of ``points (K, 2)`` (x, y): a classical change-detection cue
    (moving vehicles leave a difference of tens of grey levels, static structure only sensor noise and
    parallax). ``(K,)``."""
    return _banded(lambda a, b: cv2.blur(cv2.absdiff(a, b), (MOTION_WINDOW, MOTION_WINDOW)), (image, previous),
                   points, MOTION_WINDOW // 2)


NOISE_STRIDE = 4
"""Every this many rows and columns are sampled by :func:`frame_noise`."""


def frame_noise(image: np.ndarray, previous: np.ndarray) -> float:
    """The median absolute grey-level difference between ``image`` and the registered ``previous`` frame over a
    grid of pixels (every :data:`NOISE_STRIDE`-th row and column): most pixels are static ground, so this is the
    difference the sensor's noise leaves (about ``0.95 σ`` for white noise of ``σ`` grey levels in each frame;
    vehicles, parallax and misregistration move it little)."""
    a, b = image[::NOISE_STRIDE, ::NOISE_STRIDE], previous[::NOISE_STRIDE, ::NOISE_STRIDE]
    return float(np.median(cv2.absdiff(a, b)))


def _gradient(image: np.ndarray) -> np.ndarray:
    """Mean gradient magnitude (grey levels per px, 3×3 Sobel) over a ``MOTION_WINDOW``-px square."""
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3) / 8
    return cv2.blur(cv2.magnitude(gx, gy), (MOTION_WINDOW, MOTION_WINDOW))


def _edge(image: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """The smaller of the two frames' mean gradient magnitudes: a static edge shows in both, while where a
    vehicle moved only the frame holding it has one (its place in the other frame is road)."""
    return np.minimum(_gradient(image), _gradient(previous))


LOCAL_RADIUS = 16.0
"""Radius (px) of the neighbourhood over which :func:`local_residual` takes the corners' median error."""

LOCAL_CORNERS = 3
"""Corners a neighbourhood needs for its own residual (a vehicle holds at most one corner)."""


def local_residual(points: np.ndarray, corners: np.ndarray | None, errors: np.ndarray | None,
                   residual: float, moving: float) -> np.ndarray:
    """The registration's residual near each of ``points (K, 2)``: the median error of the registration's
    ``corners (M, 2)`` within ``LOCAL_RADIUS`` px where at least ``LOCAL_CORNERS`` lie there, else the frame's
    ``residual``. Corners whose error reaches ``moving`` px (the gate's ``min_speed``) are left out: they move
    like vehicles. On a tall building the corners share its parallax, so its neighbourhood's residual is its
    parallax. ``(K,)``."""
    out = np.full(len(points), residual, np.float64)
    if corners is not None and moving > 0:
        corners, errors = corners[errors < moving], errors[errors < moving]
    if corners is None or len(corners) < LOCAL_CORNERS or not len(points):
        return out
    near = cKDTree(corners).query_ball_point(points, LOCAL_RADIUS)
    for k, idx in enumerate(near):
        if len(idx) >= LOCAL_CORNERS:
            out[k] = np.median(errors[idx])
    return out


def misregistration(image: np.ndarray, previous: np.ndarray, residual: float | np.ndarray,
                    points: np.ndarray) -> np.ndarray:
    """The frame difference a registration error of ``residual`` px leaves at each of ``points (K, 2)``:
    ``residual · |∇I|``, the bound on ``|I(x + δ) − I(x)| ≈ |∇I · δ|`` (first order, ``|δ| = residual``), with
    ``|∇I|`` averaged over the motion window and the smaller of ``image``'s and the registered ``previous``
    frame's; ``residual`` the frame's (px) or one per point (:func:`local_residual`). Zero where it is unknown
    (NaN). ``(K,)``."""
    residual = np.broadcast_to(np.asarray(residual, np.float64), (len(points),))
    if not len(points) or not np.isfinite(residual).any():
        return np.zeros(len(points))
    return np.nan_to_num(residual) * _banded(_edge, (image, previous), points, MOTION_WINDOW // 2 + 1)


def gate_pass_fraction(image: np.ndarray, previous: np.ndarray, min_motion: float, margin: float,
                       residual: float) -> float:
    """The fraction of the frame's pixels whose motion evidence passes the moving-object gate, ``≥ min_motion
    + gate_margin(margin · misregistration)`` (computed on bands of rows, as :func:`_banded`)."""
    margin = margin * residual if np.isfinite(residual) else 0.0
    h, w = image.shape
    halo = MOTION_WINDOW // 2 + 1
    passed = 0
    for y0 in range(0, h, BAND_ROWS):
        top, bottom = max(0, y0 - halo), min(h, y0 + BAND_ROWS + halo)
        rows = slice(y0 - top, y0 - top + min(BAND_ROWS, h - y0))
        a, b = image[top:bottom], previous[top:bottom]
        motion = cv2.blur(cv2.absdiff(a, b), (MOTION_WINDOW, MOTION_WINDOW))
        need = min_motion + gate_margin(margin * _edge(a, b)) if margin else min_motion
        passed += int(np.count_nonzero((motion >= need)[rows]))
    return passed / (h * w)


TONE_WINDOW = 3
"""Side (px) of the window over which :func:`grey_level` averages the frame."""


def grey_level(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mean grey level of ``image`` over a ``TONE_WINDOW``-px square at each of ``points (K, 2)`` (x, y): the
    tone of the vehicle detected there, the attribute the GM-PHD's ``tone_sigma`` compares between frames.
    ``(K,)``."""
    return _banded(lambda a: cv2.blur(a, (TONE_WINDOW, TONE_WINDOW)), (image,), points, TONE_WINDOW // 2)


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

    Each detection's ``clutter`` is the difference the registration's residual near it leaves there
    (:func:`local_residual`, :func:`misregistration`: parallax included), which the moving-object gate adds
    to its threshold. With ``gate = (min_motion, margin, min_speed, budget, noise_factor)`` the fraction of the
    frame's pixels the plain gate (``max(min_motion, noise_factor · noise)``, ``noise`` the frame's
    :func:`frame_noise`) passes is measured (``gate_pass``; :func:`gate_pass_fraction`);
    only on a frame where it exceeds ``budget`` (and ``min_motion`` > 0) — misregistration or parallax
    showing as change over large areas — is the gate raised (``clutter`` kept, ``cluttered`` set, and
    ``gate_pass`` measured with ``margin``); elsewhere ``clutter`` is zero, and the passing pixels are the
    vehicles'. With ``scale`` the detector sees the frames resampled by that factor (its
    training scale) and its detections are mapped back. A frame the registration could not register (a new
    segment) is treated like the first: no previous frame, no prior.
    """

    def __init__(self, detector, registration: Registration, timer: StageTimer,
                 threshold: float | None = None, weak_threshold: float | None = None,
                 gate: tuple[float, float, float, float, float] | None = None, scale: float = 1.0) -> None:
        self.detector = detector
        self.scale = scale
        self.gate = gate
        self.last: RegistrationResult | None = None  # the last frame's registration
        self.gate_pass = float("nan")                  # and the fraction of its pixels the gate passes
        self.segment = 0
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
            self.last = self.registration(image)
            h = self.last.homography
            if self.last.segment != self.segment:     # a frame no search registered: start afresh
                self.segment, self.prev_image, self.prior_ref, self.prior_velocity = (
                    self.last.segment, None, np.zeros((0, 2)), None)
            h_inv = np.linalg.inv(h)
            # Previous frame resampled into the current frame: x_{k-1} = H_{k-1}^{-1} H_k x_k.
            prev = image if self.prev_image is None else warp_previous(
                self.prev_image, np.linalg.inv(self.prev_h) @ h, image.shape, fill=image)
            prior = apply_homography(self.prior_ref, h_inv)
        with self.timer("detection"):
            extra = {} if self.decode_threshold is None else {"threshold": self.decode_threshold}
            if self.takes_velocity and self.prior_velocity is not None:
                extra["prev_velocity"] = self.prior_velocity
            pos, vel, scores = self._detect(image, prev, prior, extra)
        with self.timer("registration"):
            pos_ref = apply_homography(pos, h)
            vel_ref = (homography_jacobian(h, pos) @ vel[:, :, None])[:, :, 0] if len(pos) else vel
            noise = 0.0
            if self.prev_image is None:
                vel_ref, motion = np.full_like(vel_ref, np.nan), np.full(len(pos), np.inf)
                clutter = np.zeros(len(pos))
                self.gate_pass = float("nan")
                raised = False
            else:
                motion = motion_evidence(image, prev, pos)
                if self.gate is not None and self.gate[4] > 0:     # only a noise-relative gate needs it
                    noise = frame_noise(image, prev)
                residual = local_residual(pos, self.last.corners, self.last.corner_errors, self.last.residual,
                                          self.gate[2] if self.gate else 0.0)
                clutter = misregistration(image, prev, residual, pos)
                raised = False
                if self.gate is not None:
                    min_motion, margin, _, budget, noise_factor = self.gate
                    min_motion = motion_threshold(min_motion, noise_factor, noise)
                    self.gate_pass = gate_pass_fraction(image, prev, min_motion, 0.0, self.last.residual)
                    raised = bool(margin and min_motion) and self.gate_pass > budget
                    if raised:
                        self.gate_pass = gate_pass_fraction(image, prev, min_motion, margin, self.last.residual)
                    else:
                        clutter = np.zeros(len(pos))
        self.prev_image, self.prev_h = image, h
        prior = scores >= self.prior_threshold
        self.prior_ref = pos_ref[prior]
        self.prior_velocity = None if np.isnan(vel_ref).any() else vel[prior]
        return FrameDetections(index, h, pos_ref, vel_ref, scores, pos, vel, motion, scores >= self.strong_threshold,
                               grey_level(image, pos), clutter, self.segment, raised, noise)

    def _detect(self, image: np.ndarray, prev: np.ndarray, prior: np.ndarray, extra: dict):
        """The detector on the frames resampled by ``scale`` (pixel centres kept: ``x_s = (x + ½) s − ½``), its
        positions and velocities mapped back: ``(positions, velocities, scores)`` in frame pixels."""
        s = self.scale
        if s != 1.0:
            size = (max(1, round(image.shape[1] * s)), max(1, round(image.shape[0] * s)))
            how = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
            image, prev = (cv2.resize(a, size, interpolation=how) for a in (image, prev))
            prior = (np.asarray(prior, np.float64) + 0.5) * s - 0.5
            if "prev_velocity" in extra:
                extra = {**extra, "prev_velocity": np.asarray(extra["prev_velocity"]) * s}
        found = self.detector.detect(image, prev, prior, **extra)
        pos, vel, scores = as_numpy(found.xy, (2,)), as_numpy(found.velocity, (2,)), as_numpy(found.score, ())
        if s != 1.0:
            pos, vel = (pos + 0.5) / s - 0.5, vel / s
        return pos, vel, scores

    def set_prior(self, points: np.ndarray) -> None:
        """Use ``points (N, 2)`` (reference coordinates, without velocities) for the next frame's prior heatmap
        instead of this frame's detections (``prior: tracks``)."""
        self.prior_ref = np.asarray(points, np.float64).reshape(-1, 2)
        self.prior_velocity = None
