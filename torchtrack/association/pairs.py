"""Sparse association in NumPy: the pairs of two point sets within a radius, and assignments solved per
connected component of those pairs — memory and time follow the pairs, not the product of the set sizes:
:func:`by_component` with any dense solver, :func:`max_total_assignment` (the largest total score, small
components all at once by enumeration).

NumPy only (no torch), so that scoring (``torchtrack.metrics``, ``torchtrack eval``) starts fast.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

ENUMERATED = 1000
"""Most assignments :func:`max_total_assignment` enumerates for one shape of component; larger: the Hungarian."""


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
    sdm = cKDTree(a).sparse_distance_matrix(cKDTree(b), radius, output_type="ndarray")
    return sdm["i"].astype(np.int64), sdm["j"].astype(np.int64), sdm["v"]


def _max_score(score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The assignment maximising the total of a dense block (NaN: no pair, score 0), solved as TrackEval does."""
    return linear_sum_assignment(-np.nan_to_num(score, nan=0.0))


def _present(values: np.ndarray, size: int) -> np.ndarray:
    """The distinct ``values`` (ints in [0, size)), ascending."""
    seen = np.zeros(size, bool)
    seen[values] = True
    return np.flatnonzero(seen)


def _local_index(nodes: np.ndarray, label: np.ndarray) -> np.ndarray:
    """The rank of each of the ascending ``nodes`` among the nodes of its component ``label[nodes]``."""
    order = np.argsort(label[nodes], kind="stable")
    group = label[nodes][order]
    start = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    rank = np.empty(nodes.size, np.int64)
    rank[order] = np.arange(nodes.size) - np.repeat(start, np.diff(np.r_[start, nodes.size]))
    return rank


def _segments(sorted_keys: np.ndarray) -> list[slice]:
    """The runs of equal values of ``sorted_keys``."""
    bounds = np.r_[0, np.flatnonzero(sorted_keys[1:] != sorted_keys[:-1]) + 1, sorted_keys.size]
    return [slice(lo, hi) for lo, hi in zip(bounds[:-1].tolist(), bounds[1:].tolist())]


def max_total_assignment(n: int, m: int, i: np.ndarray, j: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Positions into the pairs ``(i, j)`` of the assignment of ``n`` rows to ``m`` columns maximising the
    total ``score > 0`` (every other pair scores 0).

    The pairs' connected components are independent. A component with ``s`` rows or columns on its smaller
    side and ``L`` on the other is solved exactly by enumerating the ``L! / (L - s)!`` ways to give each of
    the ``s`` a distinct partner (all components of one shape at once) when there are at most
    :data:`ENUMERATED` of them — one row or column: its best pair; 2 x 2: the better diagonal — and by the
    Hungarian algorithm otherwise. The optimum of a dense solve; ties may break differently.
    """
    if i.size == 0:
        return np.zeros(0, np.int64)
    graph = coo_matrix((np.ones(i.size), (i, n + j)), shape=(n + m, n + m))
    count, label = connected_components(graph, directed=False)
    rows, cols = _present(i, n), n + _present(j, m)
    local = np.zeros(n + m, np.int64)
    local[rows], local[cols] = _local_index(rows, label), _local_index(cols, label)
    n_rows, n_cols = np.bincount(label[rows], minlength=count), np.bincount(label[cols], minlength=count)
    flip = (n_rows > n_cols)[label[i]]  # enumerate from the smaller side
    a, b = np.where(flip, local[n + j], local[i]), np.where(flip, local[i], local[n + j])
    small, large = np.minimum(n_rows, n_cols), np.maximum(n_rows, n_cols)
    comp = label[i]
    order = np.lexsort((comp, large[comp], small[comp]))  # by shape, then component
    won, hungarian = [], []
    for seg in _segments(small[comp][order] * (large.max() + 1) + large[comp][order]):
        mine = order[seg]
        s, size = int(small[comp[mine[0]]]), int(large[comp[mine[0]]])
        if math.perm(size, s) > ENUMERATED:
            hungarian.append(mine)
            continue
        slot = np.cumsum(np.r_[0, comp[mine][1:] != comp[mine][:-1]])
        block = np.zeros((slot[-1] + 1, s, size))
        where = np.full(block.shape, -1)
        block[slot, a[mine], b[mine]] = score[mine]
        where[slot, a[mine], b[mine]] = mine
        maps = np.array(list(itertools.permutations(range(size), s)))  # (P, s)
        best = maps[block[:, np.arange(s), maps].sum(-1).argmax(1)]  # (components, s)
        picked = where[np.arange(block.shape[0])[:, None], np.arange(s), best]
        won.append(picked[picked >= 0])
    rest = np.concatenate(hungarian) if hungarian else np.zeros(0, np.int64)
    r, k, _ = by_component(n, m, i[rest], j[rest], score[rest], _max_score)
    key = i[rest] * m + j[rest]
    at = np.argsort(key)
    pos = at[np.minimum(np.searchsorted(key[at], r * m + k), max(rest.size - 1, 0))] if rest.size else rest
    return np.concatenate([*won, rest[pos[key[pos] == r * m + k]]])
