"""Candidate pairs of 2-D points from a grid of square cells, in tensor operations (any device).

Points are sorted by cell (row-major keys); the cells of one row within a query's reach are then one run of that
order, found by two binary searches, so the pairs of a point with the cells around its own come without a
Python loop and in memory ``O(pairs in the searched cells)``, not the product of the set sizes. The result is a
superset of the pairs within each point's radius; the caller applies its exact test (a distance, a Mahalanobis
gate) to the candidates only. :func:`grid_pairs` (one set, cells of side ``max radius``, the nine cells around
each point) serves the GM-PHD's merge, :func:`grid_cross_pairs` (two sets, cells of the median radius, each
query's reach its own) the PMB's gating.
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


def _runs(query_key: Tensor, reach: Tensor, sorted_key: Tensor, order: Tensor, cols: int) -> tuple[Tensor, Tensor]:
    """Pairs ``(q, p)`` of every query (key ``query_key (Q,)``) with every point whose cell is at most ``reach_q``
    cells away along each axis (``reach (Q,)`` int64; 1: the nine cells around the query's), the points sorted
    by key (``sorted_key``, ``order`` their indices). Each of the ``2 reach + 1`` rows is one run of the order."""
    rows = 2 * reach + 1
    total = int(rows.sum())
    q_of_row = torch.arange(query_key.shape[0], device=query_key.device).repeat_interleave(rows, output_size=total)
    k = reach[q_of_row]
    row = torch.arange(total, device=query_key.device) - (torch.cumsum(rows, 0) - rows)[q_of_row] - k   # −k … k
    key = query_key[q_of_row]
    col = key % cols
    row_start = key - col + row * cols          # the runs stay inside their rows: no pair twice
    start = torch.searchsorted(sorted_key, row_start + (col - k).clamp_(min=0))
    count = torch.searchsorted(sorted_key, row_start + (col + k).clamp_(max=cols - 1), right=True) - start
    pairs = int(count.sum())
    qq = q_of_row.repeat_interleave(count, output_size=pairs)
    run_start = (torch.cumsum(count, 0) - count).repeat_interleave(count, output_size=pairs)
    offset = torch.arange(pairs, device=query_key.device) - run_start                  # position within each run
    return qq, order[start.repeat_interleave(count, output_size=pairs) + offset]


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
    return _runs(key, torch.ones_like(key), key[order], order, cols)


def grid_cross_pairs(a: Tensor, radius: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Candidate pairs ``(i, j)`` of a point ``a_i`` of ``a (A, 2)`` and a point ``b_j`` of ``b (B, 2)``: a superset of
    the pairs with ``‖a_i − b_j‖ ≤ radius_i`` (``radius (A,)``), each pair once. Cells have the side of the median
    radius, and ``a_i`` looks ``⌈radius_i / side⌉`` cells around its own, so a few wide radii (uncertain tracks)
    widen only their own search. Memory ``O(pairs in the searched cells)``."""
    if a.shape[0] == 0 or b.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.long, device=a.device)
        return empty, empty.clone()
    lo = torch.minimum(a.min(0).values, b.min(0).values)
    cell = _cell_side(lo, torch.maximum(a.max(0).values, b.max(0).values), radius.median())
    reach = torch.ceil(radius / cell).long().clamp_(min=1)
    ga, gb = _cells(a, lo, cell), _cells(b, lo, cell)
    cols = int(torch.maximum(ga[:, 0].max(), gb[:, 0].max())) + 2
    key_b = gb[:, 1] * cols + gb[:, 0]
    order = torch.argsort(key_b)
    return _runs(ga[:, 1] * cols + ga[:, 0], reach, key_b[order], order, cols)
