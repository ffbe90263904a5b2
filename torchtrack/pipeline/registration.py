"""Frame registration: a homography from each frame to a fixed reference (the first frame).

Each frame ``k`` is matched to a *keyframe* ``r`` whose map to the reference, ``H_r``, is known; its
own map is the composition

    H_k = H_r · H_{k→r},        x_ref ≃ H_k · [x, y, 1]ᵀ                                   (R1)

where ``H_{k→r}`` is estimated by RANSAC (``cv2.findHomography``, then a least-squares refit on the
inliers) from point correspondences: corners of the keyframe (Shi–Tomasi, computed over bands of rows:
:mod:`torchtrack.pipeline.corners`) followed into frame ``k`` by pyramidal
Lucas–Kanade optical flow (``lk``, the default: sub-pixel and fast), or matched ORB features (``orb``:
slower, robust to large motion). Moving objects are outliers to the camera's homography. Optionally
the estimate is refined by ECC (``cv2.findTransformECC``, which maximises the enhanced correlation of the
two images directly and is sub-pixel accurate). The keyframe is refreshed with the current frame
every ``refresh_every`` frames or when fewer than ``min_inliers`` features support the homography, so
that overlap stays large while the camera moves; the reference frame never changes, so tracks kept
in reference coordinates stay valid for the whole sequence and are drawn back into frame ``k`` by
``H_k⁻¹``.

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
from torchtrack.geometry import area_factor
from torchtrack.pipeline.corners import good_features


@dataclass
class RegistrationConfig(Checked):
    """Settings of :class:`Registration` (the ``registration:`` section of ``configs/pipeline.yaml``).

    ``method``: ``lk`` (keyframe corners + Lucas–Kanade flow + RANSAC), ``orb`` (ORB features +
    RANSAC), or ``none`` (frames already stabilised); ``ecc``: refine each estimate by ECC
    (slower; more accurate on static scenes, less with parallax, see docs/pipeline.md). ``features``:
    corners (lk) or ORB features in a frame of up to 512 × 512 px, scaled with the area of a larger one
    (:func:`torchtrack.geometry.area_factor`; see docs/scale.md for why a constant count fails on wide-area
    frames); ``window``, ``levels``: Lucas–Kanade window side (px) and
    pyramid levels above the base (the flow starts from the previous frame's estimate, so the residual
    motion to recover is small).
    """

    dotted_name: ClassVar[str] = "registration"
    method: str = option("lk", one_of=("lk", "orb", "none"))
    ecc: bool = False
    features: int = option(500, ge=4)
    window: int = option(11, ge=3)
    levels: int = option(2, ge=0)
    refresh_every: int = option(15, ge=1)
    min_inliers: int = option(40, ge=4)
    ransac_threshold: float = option(0.7, gt=0)
    ecc_iterations: int = option(30, ge=1)
    ecc_epsilon: float = option(1e-5, gt=0)


class RegistrationResult(NamedTuple):
    """``homography (3, 3)`` frame → reference, ``inliers`` supporting it, ``refreshed`` keyframe."""

    homography: np.ndarray
    inliers: int
    refreshed: bool


class Registration:
    """Stateful registration of a stream of grey ``uint8 (H, W)`` frames to the first one (R1)."""

    def __init__(self, config: RegistrationConfig | None = None) -> None:
        self.config = config or RegistrationConfig()
        if self.config.method == "orb":
            self._orb = cv2.ORB_create(nfeatures=self.config.features, fastThreshold=5)
            self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self._key_image: np.ndarray | None = None  # the keyframe and its state are set by the first frame
        self.frames = 0

    def _features(self, image: np.ndarray):
        count = math.ceil(self.config.features * area_factor(*image.shape[:2]))
        if self.config.method == "lk":
            return good_features(image, count, 0.01, 8, 7), None
        self._orb.setMaxFeatures(count)
        keypoints, descriptors = self._orb.detectAndCompute(image, None)
        return np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2), descriptors

    def _set_key(self, image: np.ndarray, h: np.ndarray, features=None) -> None:
        self._key_image = image
        self._key_h = h
        self._key_age = 0
        self._last_rel = np.eye(3)
        self._key_features = features if features is not None else self._features(image)

    def _correspondences(self, image: np.ndarray):
        """Matched points ``(src in frame, dst in keyframe)`` and the frame's ORB features (or None)."""
        key_points, key_desc = self._key_features
        cfg = self.config
        if cfg.method == "lk":
            if len(key_points) < 8:
                return np.zeros((0, 2)), np.zeros((0, 2)), None
            # Follow keyframe corners into the frame, starting from the previous frame's estimate.
            guess = cv2.perspectiveTransform(key_points, np.linalg.inv(self._last_rel)).astype(np.float32)
            moved, status, _ = cv2.calcOpticalFlowPyrLK(
                self._key_image, image, key_points, guess, winSize=(cfg.window, cfg.window), maxLevel=cfg.levels,
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
            ok = status.ravel().astype(bool)
            return moved.reshape(-1, 2)[ok], key_points.reshape(-1, 2)[ok], None
        features = self._features(image)
        points, desc = features
        if desc is None or key_desc is None or len(points) < 4 or len(key_points) < 4:
            return np.zeros((0, 2)), np.zeros((0, 2)), features
        matches = self._matcher.match(desc, key_desc)
        src = points[[m.queryIdx for m in matches]].reshape(-1, 2)
        dst = key_points[[m.trainIdx for m in matches]].reshape(-1, 2)
        return src, dst, features

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

    def __call__(self, image: np.ndarray) -> RegistrationResult:
        """Register ``image`` (grey uint8 ``(H, W)``); returns its homography to the reference."""
        if image.ndim != 2:
            raise TorchtrackError("registration expects grey (H, W) frames")
        self.frames += 1
        cfg = self.config
        if cfg.method == "none":
            return RegistrationResult(np.eye(3), 0, False)
        if self._key_image is None:
            self._set_key(image, np.eye(3))
            return RegistrationResult(np.eye(3), len(self._key_features[0]), True)
        src, dst, features = self._correspondences(image)
        rel, inliers = self._fit(src, dst)
        if rel is None or inliers < 8:
            raise TorchtrackError(
                f"registration failed at frame {self.frames}: only {inliers} point correspondences agree "
                "with one homography (is the scene textured, and the motion between frames moderate?)")
        if cfg.ecc:
            rel = self._ecc_refine(image, rel)
        h = self._key_h @ rel
        h = h / h[2, 2]
        self._key_age += 1
        self._last_rel = rel
        refresh = self._key_age >= cfg.refresh_every or inliers < cfg.min_inliers
        if refresh:
            self._set_key(image, h, features)
        return RegistrationResult(h, inliers, refresh)
