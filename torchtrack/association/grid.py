"""A spatial index on a grid of square cells (torch, any device): the candidate pairs of query discs and points.

The points are sorted by cell (row-major), with a table of where each cell's run starts, so the cells of one
grid row that a query's bounding box covers are one run of the sorted order, read from the table. A query of
radius ``r`` on cells of side ``c`` visits ``⌈2r / c⌉ + 1`` rows; the pairs returned are the points of the
covered cells, a superset of the points within ``r`` — memory and time follow the queries, the points and the
pairs near each other, not their product.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

DENSE_PAIRS = 65536
"""Up to this many query × point pairs, callers test every pair at once instead: a small problem costs fewer
operations that way than through the grid (whose fixed cost is some 40 tensor operations)."""

CELLS_PER_POINT = 16
"""Most cells of the grid per point (a finer cell is widened): the table of cell starts stays ``O(points)``."""


def disc_candidates(center: Tensor, radius: Tensor, points: Tensor, cell: float | None = None
                    ) -> tuple[Tensor, Tensor]:
    """Candidate pairs ``(q, p)`` (two ``(K,)`` long tensors, ordered by ``q``) of query discs ``center (Q, 2)``,
    ``radius (Q,)`` and ``points (P, 2)``: every pair with ``‖points[p] − center[q]‖ ≤ radius[q]`` is among
    them, and every candidate lies in a cell that the disc's bounding box covers.

    A negative radius is an empty query (no pair), an infinite one covers every point. ``cell``: the side of
    the grid's cells (default: the median finite positive radius), widened where the grid would hold more than
    :data:`CELLS_PER_POINT` cells per point. No gradient.
    """
    empty = torch.empty(0, dtype=torch.long, device=points.device)
    if center.shape[0] == 0 or points.shape[0] == 0:
        return empty, empty
    center, radius, points = center.detach(), radius.detach(), points.detach()
    lo = points.min(0).values
    extent = float((points.max(0).values - lo).max())
    if cell is None:
        finite = radius[torch.isfinite(radius) & (radius > 0)]
        cell = float(finite.median()) if finite.numel() else extent
    cell = max(cell, extent / math.sqrt(CELLS_PER_POINT * points.shape[0]), 1e-12)
    cols = int(extent / cell) + 1                                  # cells 0 … cols − 1 along both axes
    g = torch.floor((points - lo) / cell).long().clamp(0, cols - 1)
    key = g[:, 1] * cols + g[:, 0]
    order = torch.argsort(key)
    per_cell = torch.bincount(key, minlength=cols * cols)
    cell_start = torch.cat([per_cell.new_zeros(1), torch.cumsum(per_cell, 0)])    # run of cell c: [c], [c + 1]
    # the bounding box's cells, clamped into the grid (a box beside the grid gets an empty range)
    box_lo = torch.floor(((center - radius.unsqueeze(1) - lo) / cell).clamp(-1, cols)).long()
    box_hi = torch.floor(((center + radius.unsqueeze(1) - lo) / cell).clamp(-1, cols)).long()
    box_lo, box_hi = box_lo.clamp_min(0), box_hi.clamp_max(cols - 1)
    rows = (box_hi[:, 1] - box_lo[:, 1] + 1).clamp_min(0) * ((box_hi[:, 0] >= box_lo[:, 0]) & (radius >= 0))
    query = torch.repeat_interleave(torch.arange(center.shape[0], device=points.device), rows)
    row = box_lo[query, 1] + _position_in_runs(rows, query.shape[0])
    first = cell_start[row * cols + box_lo[query, 0]]
    count = cell_start[row * cols + box_hi[query, 0] + 1] - first
    total = int(count.sum())
    pair_query = torch.repeat_interleave(query, count, output_size=total)
    pair_point = order[torch.repeat_interleave(first, count, output_size=total) + _position_in_runs(count, total)]
    return pair_query, pair_point


def _position_in_runs(length: Tensor, total: int) -> Tensor:
    """``[0, 1, …, length[0] − 1, 0, 1, …, length[1] − 1, …]`` (``total = Σ length`` entries)."""
    run_start = torch.repeat_interleave(torch.cumsum(length, 0) - length, length, output_size=total)
    return torch.arange(total, device=length.device) - run_start


def nearest_within(position: Tensor, z: Tensor, max_distance: float) -> tuple[Tensor, Tensor]:
    """For each of ``position (E, 2)`` the nearest detection of ``z (M, 2)`` (the lowest index among equals):
    ``hit (E,)`` bool, one within ``max_distance``, and its index ``(E,)`` (meaningful where ``hit``). Beyond
    :data:`DENSE_PAIRS` pairs only the detections in the grid cells near each position are measured
    (:func:`disc_candidates`)."""
    E, M = position.shape[0], z.shape[0]
    if E * M <= DENSE_PAIRS:
        near, k = torch.cdist(position, z).min(dim=1)
        return near <= max_distance, k
    ee, kk = disc_candidates(position, torch.full((E,), max_distance, dtype=z.dtype, device=z.device), z,
                             cell=max_distance)
    d = (z.index_select(0, kk) - position.index_select(0, ee)).norm(dim=-1)
    best = torch.full((E,), math.inf, dtype=d.dtype, device=d.device).scatter_reduce(0, ee, d, "amin")
    tie = d == best.index_select(0, ee)
    first = torch.full((E,), M, dtype=kk.dtype, device=kk.device).scatter_reduce(0, ee[tie], kk[tie], "amin")
    return best <= max_distance, first.clamp(max=M - 1)
