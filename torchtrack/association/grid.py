"""Candidate pairs of 2-D points from a grid of square cells, in tensor operations (any device).

Points are sorted by cell (row-major keys); the three cells of a neighbouring row are then one run of that
order, found by two binary searches, so the pairs of a point with the nine cells around its own come without a
Python loop and in memory ``O(pairs in neighbouring cells)``, not the product of the set sizes. With cells of
side ``max radius`` the result is a superset of the pairs within each point's radius; the caller applies its
exact test (a distance, a Mahalanobis gate) to the candidates only.
"""

from __future__ import annotations

import torch
from torch import Tensor

MAX_CELLS = 2**20
"""At most this many cells a side, so that the row-major keys fit int64."""


def _cell_side(lo: Tensor, hi: Tensor, radius: Tensor) -> float:
    """The side of the cells: the largest radius, at least ``extent / MAX_CELLS`` (and positive)."""
    extent = float((hi - lo).max())
    return max(float(radius.max()), extent / MAX_CELLS, 1e-12)


def _cells(pos: Tensor, lo: Tensor, cell: float) -> Tensor:
    """Integer cell coordinates ``(K, 2)`` of ``pos``, with a margin cell on each side."""
    return torch.floor((pos - lo) / cell).long() + 1


def _runs(query_key: Tensor, sorted_key: Tensor, order: Tensor, cols: int) -> tuple[Tensor, Tensor]:
    """Pairs ``(q, p)`` of every query (key ``query_key (Q,)``) with every point whose cell is one of the nine
    around the query's: the points sorted by key (``sorted_key``, ``order`` their indices)."""
    first = query_key.unsqueeze(1) + torch.tensor([-cols - 1, -1, cols - 1], device=query_key.device)  # rows' first
    start = torch.searchsorted(sorted_key, first)
    count = (torch.searchsorted(sorted_key, first + 2, right=True) - start).reshape(-1)
    start = start.reshape(-1)
    qq = torch.arange(query_key.shape[0], device=query_key.device).repeat_interleave(3).repeat_interleave(count)
    run_start = (torch.cumsum(count, 0) - count).repeat_interleave(count)
    offset = torch.arange(int(count.sum()), device=query_key.device) - run_start       # position within each run
    return qq, order[start.repeat_interleave(count) + offset]


def grid_pairs(pos: Tensor, radius: Tensor) -> tuple[Tensor, Tensor]:
    """Every pair ``(i, j)`` of points ``pos (J, 2)`` whose grid cells touch, on square cells of side
    ``max radius``: a superset of the pairs with ``‖p_i − p_j‖ ≤ radius_i`` (each pair in both orders, and
    ``(i, i)``). ``radius (J,)``; memory ``O(pairs in neighbouring cells)``."""
    lo = pos.min(0).values
    cell = _cell_side(lo, pos.max(0).values, radius)
    g = _cells(pos, lo, cell)
    cols = int(g[:, 0].max()) + 2
    key = g[:, 1] * cols + g[:, 0]
    order = torch.argsort(key)
    return _runs(key, key[order], order, cols)


def grid_cross_pairs(a: Tensor, radius: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Every pair ``(i, j)`` of a point ``a_i`` of ``a (A, 2)`` and a point ``b_j`` of ``b (B, 2)`` whose grid
    cells touch, on square cells of side ``max radius``: a superset of the pairs with
    ``‖a_i − b_j‖ ≤ radius_i`` (``radius (A,)``). Memory ``O(pairs in neighbouring cells)``."""
    if a.shape[0] == 0 or b.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.long, device=a.device)
        return empty, empty.clone()
    lo = torch.minimum(a.min(0).values, b.min(0).values)
    cell = _cell_side(lo, torch.maximum(a.max(0).values, b.max(0).values), radius)
    ga, gb = _cells(a, lo, cell), _cells(b, lo, cell)
    cols = int(torch.maximum(ga[:, 0].max(), gb[:, 0].max())) + 2
    key_b = gb[:, 1] * cols + gb[:, 0]
    order = torch.argsort(key_b)
    return _runs(ga[:, 1] * cols + ga[:, 0], key_b[order], order, cols)
