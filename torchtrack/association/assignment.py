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

from collections.abc import Callable

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


def by_component(n: int, m: int, i: np.ndarray, j: np.ndarray, d: np.ndarray,
                 solve: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An assignment between ``n`` rows and ``m`` columns over the sparse pairs ``(i, j)`` with values ``d``,
    solved per connected component of the pair graph — the components are independent, so this is the
    global optimum of any rule that adds over pairs, in memory proportional to the pairs.

    ``solve`` maps a dense (rows, cols) block, NaN where no pair, to matched (rows, cols) of the block;
    a component that is a single pair is matched directly. Returns matched (i, j, d).
    """
    if i.size == 0:
        return i, j, d
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(i.size), (i, n + j)), shape=(n + m, n + m))
    _, label = connected_components(graph, directed=False)
    comp = label[i]
    single = np.bincount(comp)[comp] == 1  # an isolated pair is its own optimum
    rows, cols, dists = [i[single]], [j[single]], [d[single]]
    multi = np.flatnonzero(~single)
    order = multi[np.argsort(comp[multi], kind="stable")]
    bounds = np.flatnonzero(np.diff(comp[order])) + 1
    for idx in np.split(order, bounds) if order.size else []:  # one small dense problem per component
        ui, ii = np.unique(i[idx], return_inverse=True)
        uj, jj = np.unique(j[idx], return_inverse=True)
        sub = np.full((ui.size, uj.size), np.nan)
        sub[ii, jj] = d[idx]
        r, k = solve(sub)
        rows.append(ui[r])
        cols.append(uj[k])
        dists.append(sub[r, k])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(dists)


def gated_pairs(a: np.ndarray, b: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs of points ``a (n, 2)`` and ``b (m, 2)`` at most ``radius`` apart, found with k-d trees:
    ``(i, j, distance)``, memory proportional to the pairs rather than ``n m``."""
    from scipy.spatial import cKDTree

    sdm = cKDTree(a).sparse_distance_matrix(cKDTree(b), radius, output_type="ndarray")
    return sdm["i"].astype(np.int64), sdm["j"].astype(np.int64), sdm["v"]


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
