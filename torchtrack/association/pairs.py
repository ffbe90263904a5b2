"""Sparse association in NumPy: the pairs of two point sets within a radius, and an assignment solved per
connected component of those pairs — memory and time follow the pairs, not the product of the set sizes.

NumPy only (no torch), so that scoring (``torchtrack.metrics``, ``torchtrack eval``) starts fast.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


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
