"""Plane geometry of registered frames: homographies applied to points, their Jacobians, the warp of one
frame onto another, and the transfer error of an estimated homography against the true one.

A homography ``H (3, 3)`` maps ``p = (x, y)`` to ``π(H [p; 1])`` with ``π(q) = q[:2] / q[2]``. Used by the
video pipeline (:mod:`torchtrack.pipeline`), the detector's data and evaluation (:mod:`torchtrack.detector`)
and the video writer (:mod:`torchtrack.io.video_writer`); and the one rule by which per-frame counts scale
with the frame (:func:`area_factor`).
"""

from __future__ import annotations

import cv2
import numpy as np

from torchtrack.errors import TorchtrackError

REFERENCE_SIDE = 512
"""Side (px) of the frame for which per-frame counts are configured: the generator's roads, trees and
buildings, the detector's peak cap, the registration's features."""


def area_factor(height: int, width: int) -> float:
    """``max(1, H W / 512²)``: counts configured for a frame of up to 512 × 512 px are multiplied by it (by
    its square root for objects that are lines across the frame) so that a wide-area frame keeps their
    density instead of spreading a constant count over a larger area."""
    return max(1.0, height * width / REFERENCE_SIDE ** 2)


def apply_homography(points: np.ndarray, homography: np.ndarray | None) -> np.ndarray:
    """``points (K, 2)`` mapped by ``homography (3, 3)`` (identity when ``None``) → ``(K, 2)``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if homography is None or len(points) == 0:
        return points
    h = np.asarray(homography, dtype=np.float64)
    q = points @ h[:2, :2].T + h[:2, 2]
    w = points @ h[2, :2] + h[2, 2]
    return q / w[:, None]


def homography_jacobian(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Jacobians ``∂π(H p)/∂p (K, 2, 2)`` of the map ``p ↦ π(H [p; 1])`` at ``points (K, 2)``.

    With ``q = H [p; 1]`` and ``π(q) = q[:2] / q[2]``: ``J = (H[:2, :2] − π(q) H[2, :2]) / q[2]``.
    """
    p = np.asarray(points, np.float64).reshape(-1, 2)
    q2 = p @ h[2, :2] + h[2, 2]
    proj = apply_homography(p, h)
    return (h[None, :2, :2] - proj[:, :, None] * h[None, 2:3, :2]) / q2[:, None, None]


def transfer_error(h_est: np.ndarray, h_true: np.ndarray, shape: tuple[int, int], step: int = 16) -> np.ndarray:
    """Pixel distances ``‖π(H_est x) − π(H_true x)‖`` over a grid of frame points ``x``.

    ``h_est``, ``h_true`` ``(3, 3)`` frame → reference; ``shape`` ``(H, W)`` of the frame; ``step`` the
    grid spacing in pixels. Returns a flat array of distances (pixels, in reference coordinates).
    """
    hgt, wid = shape
    ys, xs = np.mgrid[step // 2:hgt:step, step // 2:wid:step]
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1)
    return np.linalg.norm(apply_homography(pts, h_est) - apply_homography(pts, h_true), axis=1)


def warp_previous(previous: np.ndarray, current_to_previous: np.ndarray, size: tuple[int, int],
                  offset: tuple[int, int] = (0, 0), fill: np.ndarray | None = None) -> np.ndarray:
    """The previous frame resampled onto the current one, ``out[y, x] = previous(M · [x + x0, y + y0, 1]ᵀ)``
    with ``M = current_to_previous`` (3, 3): only what moves over the ground differs between ``out`` and
    the current frame. ``size = (h, w)`` of the output, ``offset = (x0, y0)`` of its top-left corner in the
    current frame (a crop); bilinear. Where ``M`` maps outside the previous frame (a strip along the border
    after a camera motion) the previous frame's border is replicated, or with ``fill`` (the current frame,
    of shape ``size``) that pixel of ``fill`` is taken: the strip then shows no change, where replicated
    border pixels would differ from the current frame like something that moved."""
    m = np.asarray(current_to_previous, np.float64)
    if offset != (0, 0):
        m = m @ np.array([[1.0, 0.0, offset[0]], [0.0, 1.0, offset[1]], [0.0, 0.0, 1.0]])
    out = cv2.warpPerspective(previous, m, (size[1], size[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)
    if fill is None:
        return out
    fill = np.asarray(fill)
    if fill.shape != tuple(size):
        raise TorchtrackError(f"warp_previous: fill has shape {fill.shape}, the output {tuple(size)}")
    h, w = previous.shape[:2]
    inside = cv2.warpPerspective(np.ones((h, w), np.uint8), m, (size[1], size[0]),
                                 flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT)
    np.copyto(out, fill, casting="unsafe", where=inside == 0)                   # in place: no third frame
    return out
