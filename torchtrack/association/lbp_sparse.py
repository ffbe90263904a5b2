"""Loopy belief propagation on the gated pairs only: :func:`torchtrack.association.lbp.lbp_marginals` on an
edge list, so that memory and time follow the number of pairs ``E``, not ``n × m``.

The problem and the iteration are those of :mod:`torchtrack.association.lbp` (Williams & Lau 2014, with the
scaling ``a_ij = w_ij / (c_i λ_j)``, ``c_i = max(w_i0, max_j w_ij / λ_j)``)::

    μ_e = a_e / (a_i0 + Σ_{e' ∈ row i, e' ≠ e} a_e' ν_e')      ν_e = 1 / (1 + Σ_{e' ∈ column j, e' ≠ e} μ_e')

for every pair ``e = (i, j)``; a pair that is not listed has ``w_ij = 0`` (outside the gate). The sums over a
row or column are segment sums (``index_add``) and the sums "over all but one" are ``total − own``, except for
the one term per line that is above half its line's sum, whose remainder is a second sum without it (no digit
lost to cancellation, as in the dense version; there the line's first term takes that place when no term is
above half, here no term needs to). The marginals are the dense version's, up to rounding (tested to 1e-10
in float64). Plain differentiable tensor operations, any device; no batch dimension: batched problems are one
problem whose rows and columns are numbered across the batch.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.association.lbp import LOG_NEW_FLOOR
from torchtrack.errors import TorchtrackError


class SparseLBPResult(NamedTuple):
    """Marginals from :func:`sparse_lbp_marginals` for ``n`` rows (tracks), ``m`` columns (measurements) and
    ``E`` pairs."""

    row: Tensor         # (E,) track of each pair
    col: Tensor         # (E,) measurement of each pair
    assoc: Tensor       # (E,) p_i(j), track side: with ``miss`` a distribution over each row
    miss: Tensor        # (n,) p_i(0)
    new: Tensor         # (m,) p_j(new), measurement side: with ``meas_assoc`` a distribution over each column
    meas_assoc: Tensor  # (E,) p_j(i)
    iterations: int     # iterations run
    converged: bool     # max message change fell below ``tol`` (always False when ``tol`` is None)

    def assoc_matrix(self) -> Tensor:
        """``p_i(j)`` as the dense ``(n, m)`` matrix (0 off the listed pairs), as
        :class:`~torchtrack.association.lbp.LBPResult` holds it."""
        out = self.assoc.new_zeros(self.miss.shape[0], self.new.shape[0])
        return out.index_put((self.row, self.col), self.assoc)


def _check(row: Tensor, col: Tensor, log_w: Tensor, log_miss: Tensor, log_new: Tensor) -> None:
    E = log_w.shape[0]
    if log_w.dim() != 1 or row.shape != (E,) or col.shape != (E,) or log_miss.dim() != 1 or log_new.dim() != 1:
        raise TorchtrackError(f"sparse lbp: row, col and log_w must be (E,), log_miss (n,), log_new (m,); got "
                              f"{tuple(row.shape)}, {tuple(col.shape)}, {tuple(log_w.shape)}, "
                              f"{tuple(log_miss.shape)}, {tuple(log_new.shape)}")
    if E and (int(row.min()) < 0 or int(row.max()) >= log_miss.shape[0] or int(col.min()) < 0
              or int(col.max()) >= log_new.shape[0]):
        raise TorchtrackError("sparse lbp: a pair's row or column is out of range")
    for name, t in (("log_w", log_w), ("log_miss", log_miss), ("log_new", log_new)):
        if bool(torch.isnan(t).any()) or bool((t == float("inf")).any()):
            raise TorchtrackError(f"sparse lbp: {name} contains NaN or +inf")


def _line_sum(v: Tensor, line: Tensor, size: int) -> Tensor:
    """``Σ_{e ∈ line k} v_e`` for ``k = 0 … size − 1``."""
    return v.new_zeros(size).index_add(0, line, v)


def _sum_of_others(v: Tensor, line: Tensor, floor: Tensor) -> tuple[Tensor, Tensor]:
    """``floor_k + Σ_{e' ∈ line k, e' ≠ e} v_e'`` for every pair ``e`` of line ``k = line_e`` (``v ≥ 0``), and the
    lines' full sums ``floor + Σ v``. The term above half its line's sum (at most one per line) takes its
    remainder from a second sum without it, floored at the smallest normal number; every other term's is
    ``total − v_e`` with ``v_e`` at most half the total (relative error at most ``2 ε``)."""
    total = torch.index_add(floor, 0, line, v)
    total_e = total.index_select(0, line)
    with torch.no_grad():
        top = v > 0.5 * total_e
    rest = torch.index_add(floor, 0, line, v.masked_fill(top, 0.0)).clamp_min(torch.finfo(v.dtype).tiny)
    return torch.where(top, rest.index_select(0, line), total_e - v), total


def sparse_lbp_marginals(row: Tensor, col: Tensor, log_w: Tensor, log_miss: Tensor, log_new: Tensor,
                         iterations: int = 50, tol: float | None = 1e-7, check: bool = True) -> SparseLBPResult:
    """Marginal association probabilities by loopy belief propagation over the listed pairs (module docstring).

    Args:
        row, col: ``(E,)`` int64 track and measurement of each pair (each pair at most once).
        log_w: ``(E,)`` log weight of track ``row_e`` taking measurement ``col_e`` (``-inf`` allowed).
        log_miss: ``(n,)`` log weight of each track missing.
        log_new: ``(m,)`` log weight of each measurement being a new target or clutter.
        iterations, tol: as :func:`~torchtrack.association.lbp.lbp_marginals` (``tol=None``: fixed iterations).
        check: validate shapes, indices and values (host synchronisations).

    Returns:
        :class:`SparseLBPResult`; dtype and device follow ``log_w``; differentiable in the three weights.
    """
    if check:
        _check(row, col, log_w, log_miss, log_new)
    if iterations < 1:
        raise TorchtrackError(f"sparse lbp: iterations must be >= 1; got {iterations}")
    n, m = log_miss.shape[0], log_new.shape[0]
    log_new = log_new.clamp_min(LOG_NEW_FLOOR.get(log_new.dtype, LOG_NEW_FLOOR[torch.float32]))
    log_ratio = log_w - log_new[col]                                           # log(w_ij / λ_j)
    with torch.no_grad():                                                      # c_i: the marginals do not depend on it
        log_c = log_miss.detach().clone().scatter_reduce(0, row, log_ratio.detach(), "amax")
        finite = torch.isfinite(log_c)
        log_c = torch.where(finite, log_c, torch.zeros_like(log_c))
    a = torch.exp(log_ratio - log_c.index_select(0, row))                      # (E,)
    a0 = torch.exp(torch.where(finite, log_miss - log_c, torch.zeros_like(log_c)))   # (n,); 1 without any weight
    one = torch.ones(m, dtype=a.dtype, device=a.device)
    tiny = torch.finfo(a.dtype).tiny
    prod, last, it, converged = a, None, 0, False                              # ν = 1
    for it in range(1, iterations + 1):
        others, t = _sum_of_others(prod, row, a0)
        mu = a / others                                                        # track → measurement
        others, s = _sum_of_others(mu, col, one)
        prod = a / others                                                      # a_e ν_e, measurement → track
        if tol is not None and (it % 2 == 0 or it == iterations):
            stat = torch.cat([a0 / t, s.reciprocal()]).detach()
            if last is not None and (stat.numel() == 0 or float((stat - last).abs().amax()) < tol):
                converged = True
                break
            last = stat
    t = (_line_sum(prod, row, n) + a0).clamp_min(tiny)
    others, _ = _sum_of_others(prod, row, a0)
    mu = a / others                                                            # μ from the final ν
    s = (_line_sum(mu, col, m) + 1.0).clamp_min(tiny)
    return SparseLBPResult(row, col, prod / t[row], a0 / t, s.reciprocal(), mu / s[col], it, converged)
