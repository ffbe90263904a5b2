"""Discrete measurement-to-track assignment: Hungarian (global nearest neighbour) and greedy.

This is the one place where tensors leave the graph for the host: the solvers are combinatorial,
run on ``numpy`` copies (``scipy.optimize.linear_sum_assignment``) and their result is an explicit
stop-gradient selection. Costs are built batched by the callers (gates, likelihoods); only the solve
loops over the batch.

Gating: ``valid (R, C)`` marks the admissible (gated) pairs; a pair outside the gate is never returned.

* Without ``unassigned_cost`` the Hungarian solve is the classic GNN rule: the largest number of
  gated pairs, and among those the smallest total cost (inadmissible pairs get a cost larger than any
  sum of admissible ones and are dropped afterwards).
* With ``unassigned_cost = c₀`` every row and every column may also stay unassigned at cost ``c₀``
  each (the matrix is augmented to ``(R + C) × (C + R)``, Blackman & Popoli 1999 §6.5), so a pair
  ``(i, j)`` is only used when ``cost[i, j] < 2 c₀`` helps the total.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError


def _as_numpy(x) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _prepare(cost, valid) -> tuple[np.ndarray, np.ndarray]:
    c = _as_numpy(cost).astype(np.float64)
    if c.ndim != 2:
        raise TorchtrackError(f"assignment cost must be a (rows, cols) matrix; got shape {c.shape}")
    ok = np.isfinite(c)
    if valid is not None:
        v = _as_numpy(valid).astype(bool)
        if v.shape != c.shape:
            raise TorchtrackError(f"assignment valid mask shape {v.shape} != cost shape {c.shape}")
        ok &= v
    return c, ok


def hungarian(cost, valid=None, unassigned_cost: float | None = None) -> tuple[Tensor, Tensor]:
    """Optimal assignment over gated pairs of one ``cost (R, C)`` matrix (tensor or array).

    ``valid (R, C)`` bool marks admissible pairs (non-finite costs are inadmissible too). Returns
    ``(rows, cols)``, two ``int64`` tensors of the matched pairs, sorted by row.
    """
    from scipy.optimize import linear_sum_assignment

    c, ok = _prepare(cost, valid)
    R, C = c.shape
    empty = torch.zeros(0, dtype=torch.long)
    if R == 0 or C == 0 or not ok.any():
        return empty, empty
    if unassigned_cost is None:
        big = 2.0 * np.abs(c[ok]).sum() + 1.0
        work = np.where(ok, c, big)
        r, k = linear_sum_assignment(work)
    else:
        c0 = float(unassigned_cost)
        big = 2.0 * (np.abs(c[ok]).sum() + abs(c0) * (R + C)) + 1.0
        work = np.full((R + C, C + R), big)
        work[:R, :C] = np.where(ok, c, big)
        work[np.arange(R), C + np.arange(R)] = c0
        work[R + np.arange(C), np.arange(C)] = c0
        work[R:, C:] = 0.0
        r, k = linear_sum_assignment(work)
        inside = (r < R) & (k < C)
        r, k = r[inside], k[inside]
    keep = ok[r, k]
    return torch.as_tensor(r[keep], dtype=torch.long), torch.as_tensor(k[keep], dtype=torch.long)


def greedy(cost, valid=None, unassigned_cost: float | None = None) -> tuple[Tensor, Tensor]:
    """Greedy assignment: repeatedly take the cheapest admissible pair whose row and column are free.

    Same arguments and result as :func:`hungarian`; with ``unassigned_cost`` pairs costing
    ``≥ 2 c₀`` are not taken (the break-even of leaving both ends unassigned).
    """
    c, ok = _prepare(cost, valid)
    if unassigned_cost is not None:
        ok &= c < 2.0 * float(unassigned_cost)
    rows, cols = np.nonzero(ok)
    order = np.argsort(c[rows, cols], kind="stable")
    taken: dict[int, int] = {}                     # row → its column
    used = set()
    for i, j in zip(rows[order].tolist(), cols[order].tolist()):
        if i not in taken and j not in used:
            taken[i] = j
            used.add(j)
    matched = sorted(taken)
    return (torch.as_tensor(matched, dtype=torch.long),
            torch.as_tensor([taken[i] for i in matched], dtype=torch.long))


_SOLVERS = {"hungarian": hungarian, "greedy": greedy}


def assign(cost: Tensor, valid: Tensor | None = None, method: str = "hungarian",
           unassigned_cost: float | None = None) -> Tensor:
    """Batched assignment: ``cost (*, R, C)`` → the column assigned to each row, ``(*, R)`` int64, ``-1``
    where unassigned. ``valid (*, R, C)`` marks gated pairs. The result lives on ``cost``'s device.

    This is an explicit stop-gradient selection (the returned indices carry no gradient).
    """
    if method not in _SOLVERS:
        raise TorchtrackError(f"assignment method must be one of {sorted(_SOLVERS)}; got {method!r}")
    if cost.dim() < 2:
        raise TorchtrackError(f"assignment cost must have shape (*, rows, cols); got {tuple(cost.shape)}")
    solve = _SOLVERS[method]
    batch, (R, C) = cost.shape[:-2], cost.shape[-2:]
    c = cost.detach().reshape(-1, R, C).cpu()
    v = None if valid is None else valid.expand_as(cost).reshape(-1, R, C).cpu()
    out = torch.full((c.shape[0], R), -1, dtype=torch.long)
    for b in range(c.shape[0]):
        r, k = solve(c[b], None if v is None else v[b], unassigned_cost)
        out[b, r] = k
    return out.reshape(*batch, R).to(cost.device)


__all__ = ["assign", "greedy", "hungarian"]
