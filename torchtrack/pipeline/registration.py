"""Frame registration: a homography from each frame to a fixed reference (the first frame of its segment).

Each frame ``k`` is matched to a *keyframe* ``r`` whose map to the reference, ``H_r``, is known; its
own map is the composition

    H_k = H_r · H_{k→r},        x_ref ≃ H_k · [x, y, 1]ᵀ                                   (R1)

where ``H_{k→r}`` is estimated by RANSAC (``cv2.findHomography``, then a least-squares refit on the
inliers) from point correspondences: corners of the keyframe (Shi–Tomasi, computed over bands of rows:
:mod:`torchtrack.pipeline.corners`) followed into frame ``k`` by pyramidal Lucas–Kanade optical flow
(``lk``, the default: sub-pixel and fast), or matched ORB features (``orb``). Moving objects are outliers
to the camera's homography. Optionally the estimate is refined by ECC (``cv2.findTransformECC``). The
keyframe is renewed with the current frame every ``refresh_every`` frames, when fewer than ``min_inliers``
corners (or ``min_inlier_fraction`` of those followed) agree, and when the frame-to-frame residual (below)
exceeds ``max_residual`` (``lk`` only): then the frame is first registered again against the previous frame
(chained), and the estimate with the smaller residual is kept. A keyframe held over several frames drifts less on a flat
static scene; on a real camera, parallax and changes of view make it stale, and the chain takes over.

A real camera moves fast and jumps. The flow starts from a constant-motion prediction

    H_{k→r} ≈ H_{k-1→r} · H_{k→k-1}^{pred},     H_{k→k-1}^{pred} = H_{k-1→k-2}                (R2)

and when fewer than ``min_inliers`` corners agree with one homography, two wider searches follow: the
translation found by phase correlation of the two frames at a quarter of their size (any shift up to half
the frame) as the flow's start, then ORB features matched over the whole frame. A frame that none of them
registers starts a new *segment* (``RegistrationResult.segment``): it becomes the keyframe with the
prediction (R2) as its map, and the pipeline restarts its tracks there instead of stopping.

Every frame after the first of a segment gets a **frame-to-frame residual** (px): corners of the previous
frame (its own where it is the keyframe, else the keyframe's corners where the flow found them in it) are
followed into this frame by Lucas–Kanade flow started where the estimated homographies put
them, ``x̂ = H_k⁻¹ H_{k-1} x``; the residual is the median distance between where the flow finds them
and ``x̂``. The median is over all corners, so moving vehicles (a minority) do not count, while a
homography that is wrong for the scene does.

:func:`torchtrack.geometry.transfer_error` measures a registration against the true camera motion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import cv2
import numpy as np

from torchtrack.config import Checked, option
from torchtrack.errors import TorchtrackError
from torchtrack.geometry import apply_homography, area_factor
from torchtrack.pipeline.corners import good_features

PHASE_SCALE = 0.25
"""Resampling of the frames for the phase-correlation search (a jump of up to half the frame)."""


@dataclass
class RegistrationConfig(Checked):
    """Settings of :class:`Registration` (the ``registration:`` section of ``configs/pipeline.yaml``).

    ``method``: ``lk`` (keyframe corners + Lucas–Kanade flow + RANSAC), ``orb`` (ORB features +
    RANSAC), or ``none`` (frames already stabilised); ``ecc``: refine each estimate by ECC
    (slower; more accurate on static scenes, less with parallax, see docs/pipeline.md). ``features``:
    corners (lk) or ORB features in a frame of up to 512 × 512 px, scaled with the area of a larger one
    (:func:`torchtrack.geometry.area_factor`; see docs/scale.md for why a constant count fails on wide-area
    frames); ``window``, ``levels``: Lucas–Kanade window side (px) and pyramid levels above the base (the
    flow starts from the prediction (R2), so the motion left to recover is small). ``refresh_every``:
    frames a keyframe serves (1: chained frame to frame); ``min_inliers``, ``min_inlier_fraction``: below
    either, the keyframe is renewed and, if the estimate has fewer than ``min_inliers`` inliers, the wider
    searches (module docstring) run (``recover: false``: they do not); a frame whose best estimate still has
    fewer than ``min_inliers`` (8 with the prediction's own estimate) starts a new segment.
    """

    dotted_name: ClassVar[str] = "registration"
    method: str = option("lk", one_of=("lk", "orb", "none"))
    ecc: bool = False
    features: int = option(500, ge=4)
    window: int = option(11, ge=3)
    levels: int = option(3, ge=0)
    refresh_every: int = option(15, ge=1)
    max_residual: float = option(0.5, gt=0)
    min_inliers: int = option(40, ge=4)
    min_inlier_fraction: float = option(0.3, ge=0, le=1)
    ransac_threshold: float = option(0.7, gt=0)
    recover: bool = True
    ecc_iterations: int = option(30, ge=1)
    ecc_epsilon: float = option(1e-5, gt=0)


class RegistrationResult(NamedTuple):
    """``homography (3, 3)`` frame → reference, ``inliers`` supporting it, ``refreshed`` keyframe, ``residual``
    the frame-to-frame residual (px; NaN on a segment's first frame), ``segment`` (0, 1, …: a frame that
    could not be registered starts the next), ``search`` the search that registered it (``predicted``,
    ``phase``, ``orb``, ``first``: a segment's first frame); ``corners (M, 2)`` where the previous frame's corners
    were found in this frame and ``corner_errors (M,)`` their distances (px) from where the homographies put
    them: the residual's samples, large on tall structures (parallax) and on moving vehicles."""

    homography: np.ndarray
    inliers: int
    refreshed: bool
    residual: float = math.nan
    segment: int = 0
    search: str = "predicted"
    corners: np.ndarray | None = None
    corner_errors: np.ndarray | None = None


class Registration:
    """Stateful registration of a stream of grey ``uint8 (H, W)`` frames to the first one (R1, R2)."""

    def __init__(self, config: RegistrationConfig | None = None) -> None:
        self.config = config or RegistrationConfig()
        self._orb = cv2.ORB_create(nfeatures=self.config.features, fastThreshold=5)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self._key_image: np.ndarray | None = None  # the keyframe and its state are set by the first frame
        self.frames = 0
        self.segment = -1

    def _count(self, image: np.ndarray) -> int:
        return math.ceil(self.config.features * area_factor(*image.shape[:2]))

    def _corners(self, image: np.ndarray) -> np.ndarray:
        return good_features(image, self._count(image), 0.01, 8, 7)

    def _orb_features(self, image: np.ndarray, count: int):
        self._orb.setMaxFeatures(count)
        keypoints, descriptors = self._orb.detectAndCompute(image, None)
        return np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2), descriptors

    def _features(self, image: np.ndarray):
        if self.config.method == "lk":
            return self._corners(image), None
        return self._orb_features(image, self._count(image))

    def _set_key(self, image: np.ndarray, h: np.ndarray, features=None) -> None:
        self._key_image = image
        self._key_h = h
        self._key_age = 0
        self._last_rel = np.eye(3)
        self._key_features = features if features is not None else self._features(image)

    def _start_segment(self, image: np.ndarray, h: np.ndarray) -> None:
        self.segment += 1
        self._set_key(image, h)
        self._step = np.eye(3)                   # H_{k-1→k-2}, the prediction (R2)
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        self._prev_points: np.ndarray | None = None  # where the keyframe's corners were found in the previous frame

    def _flow(self, key_points: np.ndarray, image: np.ndarray, rel_guess: np.ndarray, levels: int):
        """Keyframe corners followed into ``image`` from where ``rel_guess`` (frame → keyframe) puts them:
        ``(src in frame, dst in keyframe)``."""
        cfg = self.config
        if len(key_points) < 8:
            return np.zeros((0, 2)), np.zeros((0, 2))
        guess = cv2.perspectiveTransform(key_points, np.linalg.inv(rel_guess)).astype(np.float32)
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            self._key_image, image, key_points, guess, winSize=(cfg.window, cfg.window), maxLevel=levels,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        ok = status.ravel().astype(bool)
        return moved.reshape(-1, 2)[ok], key_points.reshape(-1, 2)[ok]

    def _orb_match(self, features, key_features):
        (points, desc), (key_points, key_desc) = features, key_features
        if desc is None or key_desc is None or len(points) < 4 or len(key_points) < 4:
            return np.zeros((0, 2)), np.zeros((0, 2))
        matches = self._matcher.match(desc, key_desc)
        src = points[[m.queryIdx for m in matches]].reshape(-1, 2)
        dst = key_points[[m.trainIdx for m in matches]].reshape(-1, 2)
        return src, dst

    def _fit(self, src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray | None, int]:
        if len(src) < 8:
            return None, 0
        h, mask = cv2.findHomography(src, dst, cv2.RANSAC, self.config.ransac_threshold, maxIters=2000,
                                     confidence=0.999)
        if h is None:
            return None, 0
        inl = mask.ravel().astype(bool)
        if inl.sum() >= 8:
            # Least-squares refit on the inliers (RANSAC's estimate comes from a minimal sample).
            refit, _ = cv2.findHomography(src[inl], dst[inl], 0)
            if refit is not None:
                h = refit
        return h, int(inl.sum())

    def _phase_shift(self, image: np.ndarray) -> np.ndarray:
        """Frame → keyframe translation found by phase correlation of the two frames at ``PHASE_SCALE``."""
        small = [cv2.resize(im, None, fx=PHASE_SCALE, fy=PHASE_SCALE, interpolation=cv2.INTER_AREA).astype(np.float32)
                 for im in (self._key_image, image)]
        window = cv2.createHanningWindow(small[0].shape[::-1], cv2.CV_32F)
        (dx, dy), _ = cv2.phaseCorrelate(small[0], small[1], window)
        return np.array([[1, 0, -dx / PHASE_SCALE], [0, 1, -dy / PHASE_SCALE], [0, 0, 1]], np.float64)

    def _estimate(self, image: np.ndarray) -> tuple[np.ndarray | None, int, np.ndarray, str, object]:
        """Frame → keyframe homography: ``(rel or None, inliers, the correspondences' points in the frame,
        search, frame's features)``."""
        cfg = self.config
        predicted = self._last_rel @ self._step
        if cfg.method == "orb":
            features = self._features(image)
            src, dst = self._orb_match(features, self._key_features)
            rel, inliers = self._fit(src, dst)
            return rel, inliers, src, "orb", features
        src, dst = self._flow(self._key_features[0], image, predicted, cfg.levels)
        rel, inliers = self._fit(src, dst)
        best = (rel, inliers, src, "predicted", None)
        if inliers >= cfg.min_inliers or not cfg.recover:
            return best
        src, dst = self._flow(self._key_features[0], image, self._phase_shift(image), cfg.levels)
        rel, inliers = self._fit(src, dst)
        if inliers > best[1]:
            best = (rel, inliers, src, "phase", None)
        if best[1] >= cfg.min_inliers:
            return best
        count = 4 * self._count(image)
        src, dst = self._orb_match(self._orb_features(image, count), self._orb_features(self._key_image, count))
        rel, inliers = self._fit(src, dst)
        if inliers > best[1]:
            best = (rel, inliers, src, "orb", None)
        return best

    def _ecc_refine(self, image: np.ndarray, init: np.ndarray) -> np.ndarray:
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.config.ecc_iterations,
                    self.config.ecc_epsilon)
        try:
            # ECC finds W with template(x) ≈ input(W x); template = frame, input = keyframe, so W is
            # the frame → keyframe map itself.
            _, w = cv2.findTransformECC(image, self._key_image, (init / init[2, 2]).astype(np.float32),
                                        cv2.MOTION_HOMOGRAPHY, criteria, None, 5)
        except cv2.error:
            return init
        return w.astype(np.float64)

    def _residual(self, image: np.ndarray, h: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """The frame-to-frame residual (px) of ``h`` (module docstring), the corners found in ``image`` and
        their errors."""
        prev_image, prev_h = self._prev
        lk = self.config.method == "lk"
        if lk and self._key_age == 0:
            points = self._key_features[0].reshape(-1, 2)       # the keyframe is the previous frame
        elif lk and self._prev_points is not None and len(self._prev_points) >= 8:
            points = self._prev_points.astype(np.float32)       # the keyframe's corners, followed into it
        else:
            points = self._corners(prev_image).reshape(-1, 2)
        none = (math.nan, np.zeros((0, 2)), np.zeros(0))
        if len(points) == 0:
            return none
        predicted = apply_homography(points, np.linalg.inv(h) @ prev_h).astype(np.float32)
        cfg = self.config
        found, status, _ = cv2.calcOpticalFlowPyrLK(
            prev_image, image, points.reshape(-1, 1, 2), predicted.reshape(-1, 1, 2).copy(),
            winSize=(cfg.window, cfg.window), maxLevel=1, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        ok = status.ravel().astype(bool)
        if not ok.any():
            return none
        found = found.reshape(-1, 2)[ok]
        errors = np.hypot(*(found - predicted[ok]).T)
        return float(np.median(errors)), found.astype(np.float64), errors.astype(np.float64)

    def _register(self, image: np.ndarray):
        """This frame against the keyframe, without changing the state: ``(rel, h, inliers, tracked, search,
        features, residual)``, ``rel`` None where no search registered it."""
        rel, inliers, tracked, search, features = self._estimate(image)
        if rel is None or inliers < min(self.config.min_inliers, 8) or (
                search != "predicted" and inliers < self.config.min_inliers):
            return None, None, inliers, tracked, search, features, (math.nan, None, None)
        if self.config.ecc:
            rel = self._ecc_refine(image, rel)
        h = self._key_h @ rel
        h = h / h[2, 2]
        return rel, h, inliers, tracked, search, features, self._residual(image, h)

    def __call__(self, image: np.ndarray) -> RegistrationResult:
        """Register ``image`` (grey uint8 ``(H, W)``); returns its homography to the reference."""
        if image.ndim != 2:
            raise TorchtrackError("registration expects grey (H, W) frames")
        self.frames += 1
        cfg = self.config
        if cfg.method == "none":
            return RegistrationResult(np.eye(3), 0, False, math.nan, 0, "none")
        if self._key_image is None:
            self._start_segment(image, np.eye(3))
            self._prev = (image, np.eye(3))
            return RegistrationResult(np.eye(3), len(self._key_features[0]), True, math.nan, self.segment, "first")
        if image.shape != self._key_image.shape:
            (h, w), (kh, kw) = image.shape, self._key_image.shape
            raise TorchtrackError(f"frame {self.frames} is {w}x{h} px, the earlier ones {kw}x{kh}: all frames must "
                                  "have one size")
        rel, h, inliers, tracked, search, features, measured = self._register(image)
        if cfg.method == "lk" and self._key_age > 0 and not measured[0] <= cfg.max_residual:
            # The keyframe has grown stale (parallax, a changed view): register against the previous frame.
            saved = (self._key_image, self._key_h, self._key_age, self._last_rel, self._key_features)
            self._set_key(*self._prev)
            retry = self._register(image)
            if retry[0] is not None and not retry[-1][0] >= measured[0]:
                rel, h, inliers, tracked, search, features, measured = retry
            else:
                self._key_image, self._key_h, self._key_age, self._last_rel, self._key_features = saved
        if rel is None:
            h = self._key_h @ self._last_rel @ self._step
            h = h / h[2, 2]
            self._start_segment(image, h)
            self._prev = (image, h)
            return RegistrationResult(h, inliers, True, math.nan, self.segment, "first")
        self._key_age += 1
        self._prev_points = tracked.reshape(-1, 2)
        self._step = np.linalg.inv(self._last_rel) @ rel       # H_{k→k-1}
        self._last_rel = rel
        self._prev = (image, h)
        residual = measured[0]
        refresh = (self._key_age >= cfg.refresh_every or inliers < cfg.min_inliers
                   or inliers < cfg.min_inlier_fraction * len(tracked)
                   or (cfg.method == "lk" and not residual <= cfg.max_residual))
        if refresh:
            self._set_key(image, h, features)
        return RegistrationResult(h, inliers, refresh, residual, self.segment, search, *measured[1:])
