"""Detections simulated from ground truth: missed detections, position noise, Poisson clutter, velocities.

For every truth object ``i`` present in frame ``k`` at centre ``p_i(k)`` (column, row):

- it is detected with probability ``p_D`` (independently);
- a detection is ``z = p_i(k) + e``, ``e ~ N(0, sigma^2 I_2)`` (pixels);
- with ``velocity_sigma`` given, the detection also carries a velocity ``v = u_i(k) + w``,
  ``w ~ N(0, velocity_sigma^2 I_2)`` (px/frame), where ``u_i(k)`` is the truth's finite difference
  ``(p_i(k) - p_i(k')) / (k - k')`` to the object's previous frame ``k'`` (forward difference on its first
  frame, 0 for an object seen once). This stands in for the CenterTrack-style detector's velocity head.

Every frame from the first to the last truth frame also receives ``Poisson(clutter)`` false detections,
uniform over the image ``[0, W) x [0, H)``, whose velocities (when asked for) are ``N(0, velocity_sigma^2 I_2)``.
Detections are unlabelled (id -1), confidence 1, boxes of ``box`` px, sorted by frame and shuffled within a
frame (their order carries no information about the truth). All randomness comes from ``generator``, so
the same seed gives the same detections, and the same positions with or without velocities.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import POINT_BOX_SIZE, MOTData, from_points

MAX_CLUTTER = 5e7
"""Most false detections a simulation draws in all (about 4 GB of detections): more is refused up front."""


class SimulatedDetections(NamedTuple):
    """``detections`` (id -1) and, per detection, the truth id it came from (``source``, -1 for clutter)."""

    detections: MOTData
    source: np.ndarray


def truth_velocity(truth: MOTData) -> np.ndarray:
    """(K, 2) finite-difference velocity (px/frame) of every truth line, in ``truth``'s order (see module)."""
    order = np.lexsort((truth.frame, truth.id))
    ids, frames = truth.id[order], truth.frame[order]
    pos = truth.centers()[order]
    vel = np.zeros_like(pos)
    if truth.size > 1:
        same = ids[1:] == ids[:-1]
        step = (pos[1:] - pos[:-1]) / np.maximum(frames[1:] - frames[:-1], 1)[:, None]
        back = np.flatnonzero(same) + 1
        vel[back] = step[back - 1]
        first = np.flatnonzero(np.r_[True, ~same])  # the first line of each object seen twice or more
        first = first[first < ids.size - 1]
        first = first[same[first]]
        vel[first] = step[first]  # takes the forward difference
    out = np.empty_like(vel)
    out[order] = vel
    return out


def simulate_detections(
    truth: MOTData,
    pd: float,
    sigma: float,
    clutter: float,
    image_size: tuple[float, float],
    velocity_sigma: float | None = None,
    generator: torch.Generator | None = None,
    box: float = POINT_BOX_SIZE,
) -> SimulatedDetections:
    """Simulate a detector on ``truth`` (module docstring for the model).

    Args:
        truth: ground truth (ids >= 0).
        pd: detection probability in [0, 1].
        sigma: position noise standard deviation in px (>= 0).
        clutter: mean number of false detections per frame (>= 0), in each frame that the truth holds (the
            frames present, so frame numbers may be anything, timestamps included).
        image_size: ``(W, H)`` in px, the clutter region.
        velocity_sigma: velocity noise in px/frame; None for detections without velocity.
        generator: torch random generator (a fresh unseeded one when None).
        box: side of the point boxes written.
    """
    if not 0 <= pd <= 1:
        raise TorchtrackError(f"pd must be in [0, 1], got {pd}")
    if not sigma >= 0 or not clutter >= 0:
        raise TorchtrackError(f"sigma and clutter must be >= 0, got {sigma}, {clutter}")
    if velocity_sigma is not None and not velocity_sigma >= 0:
        raise TorchtrackError(f"velocity_sigma must be >= 0, got {velocity_sigma}")
    width, height = (float(v) for v in image_size)
    if not (width > 0 and height > 0):
        raise TorchtrackError(f"image_size must be positive, got {image_size}")
    frames = truth.frames()
    if clutter * frames.size > MAX_CLUTTER:
        raise TorchtrackError(f"clutter {clutter:g} per frame over {frames.size} frames is more than "
                              f"{MAX_CLUTTER:.0e} false detections in all")
    g = generator if generator is not None else torch.Generator()
    f64 = torch.float64

    k = truth.size
    detected = (torch.rand(k, generator=g, dtype=f64) < pd).numpy()
    pos = truth.centers() + sigma * torch.randn(k, 2, generator=g, dtype=f64).numpy()
    vel_noise = torch.randn(k, 2, generator=g, dtype=f64).numpy()

    counts = torch.poisson(torch.full((frames.size,), float(clutter), dtype=f64), generator=g).long().numpy()
    n_clutter = int(counts.sum())
    clutter_pos = torch.rand(n_clutter, 2, generator=g, dtype=f64).numpy() * np.array([width, height])
    clutter_vel = torch.randn(n_clutter, 2, generator=g, dtype=f64).numpy()

    det_frames = np.concatenate([truth.frame[detected], np.repeat(frames, counts)])
    det_pos = np.concatenate([pos[detected], clutter_pos])
    source = np.concatenate([truth.id[detected], np.full(n_clutter, -1, dtype=np.int64)])
    vx = vy = None
    if velocity_sigma is not None:
        vel = np.concatenate([truth_velocity(truth)[detected] + velocity_sigma * vel_noise[detected],
                              velocity_sigma * clutter_vel])
        vx, vy = vel[:, 0], vel[:, 1]
    shuffle = torch.rand(det_frames.size, generator=g, dtype=f64).numpy()
    order = np.lexsort((shuffle, det_frames))
    det = from_points(det_frames, np.full(det_frames.size, -1), det_pos[:, 0], det_pos[:, 1], box=box,
                      vx=vx, vy=vy).select(order)
    return SimulatedDetections(det, source[order])


def default_image_size(truth: MOTData) -> tuple[int, int]:
    """``(W, H)`` just covering the truth centres: ``floor(max) + 1`` of each coordinate (1 when empty)."""
    if truth.size == 0:
        return 1, 1
    top = np.floor(truth.centers().max(axis=0)).astype(int) + 1
    return max(int(top[0]), 1), max(int(top[1]), 1)
