"""The clutter measured where no target is: the density κ and the velocity spread τ of false detections, from
the cells of the image that no track crosses (docs/calibrate.md, "Clutter").

The region is cut into square cells of ``cell`` px; a cell is *tracked* when a track's smoothed position comes
within ``margin`` px of it at any frame. Over the ``T`` frames of the window, a cell without tracks collects
``Poisson(κ cell² T)`` false detections, plus the detections of targets the tracker never followed. The median
over those cells is robust to the latter while they hold a minority of the cells, and the Poisson median is
``λ + 1/3`` to within ``1/(50 λ)`` (Choi 1994), so ``κ = (median − 1/3) / (cell² T)``. The clutter's
velocities are taken as ``N(0, τ² I)``: ``|v|² / τ²`` is χ²₂, whose median is ``2 ln 2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Background:
    """κ (px⁻² per frame) and τ (px/frame; None without velocities) with standard errors, and the cells used."""

    clutter_density: float
    clutter_density_stderr: float
    clutter_velocity_sigma: float | None
    clutter_velocity_sigma_stderr: float | None
    cells: int


def measure_background(positions: list[np.ndarray], velocities: list[np.ndarray] | None,
                       region: tuple[float, float, float, float], track_points: np.ndarray,
                       cell: float = 32.0, margin: float = 8.0) -> Background | None:
    """κ and τ from the detections ``positions[k] (K, 2)`` (``velocities`` likewise, or None) of the frames of
    the window, in the cells of ``region`` that no point of ``track_points (N, 2)`` comes within ``margin`` of;
    None when no such cell exists."""
    x0, y0, x1, y1 = region
    nx, ny = int((x1 - x0) // cell), int((y1 - y0) // cell)
    if nx < 1 or ny < 1:
        return None
    tracked = np.zeros((ny, nx), bool)
    for dx in (-margin, 0.0, margin):
        for dy in (-margin, 0.0, margin):
            ix = np.floor((track_points[:, 0] + dx - x0) / cell).astype(np.int64)
            iy = np.floor((track_points[:, 1] + dy - y0) / cell).astype(np.int64)
            ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
            tracked[iy[ok], ix[ok]] = True
    if tracked.all():
        return None
    pts = np.concatenate(positions)
    ix = np.floor((pts[:, 0] - x0) / cell).astype(np.int64)
    iy = np.floor((pts[:, 1] - y0) / cell).astype(np.int64)
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    counts = np.zeros((ny, nx))
    np.add.at(counts, (iy[inside], ix[inside]), 1.0)
    free = counts[~tracked]
    frames = len(positions)
    exposure = cell * cell * frames
    kappa = max(float(np.median(free)) - 1.0 / 3.0, 0.5) / exposure
    kappa_se = 1.2533 * math.sqrt(kappa * exposure) / math.sqrt(free.size) / exposure
    tau = tau_se = None
    if velocities is not None:
        vel = np.concatenate(velocities)
        pick = inside.copy()
        pick[inside] = ~tracked[iy[inside], ix[inside]]
        speed2 = np.sum(vel[pick] ** 2, 1)
        if speed2.size:
            tau = math.sqrt(float(np.median(speed2)) / (2 * math.log(2)))
            tau_se = 1.2533 * tau / math.sqrt(2 * speed2.size)
    return Background(kappa, kappa_se, tau, tau_se, int(free.size))
