"""The GLMB's gated likelihoods (G2 of :mod:`torchtrack.filters.glmb.filter`): for each predicted row its measurements
inside the gate, best first, as a padded ``(N, K)`` table.

A small frame (``N M ≤`` :data:`~torchtrack.association.grid.DENSE_PAIRS`) whitens every row–measurement
innovation at once and keeps the ``K`` best per row (``topk``); a larger one takes its candidate pairs from the
shared grid index (:func:`torchtrack.filters.gmphd.filter.gated_pairs`, which misses no pair inside the gate)
and whitens only those, so memory and time follow the pairs near each other, not ``N M``. Both give the same table
(the same pairs, each row's candidates by decreasing likelihood; values equal to rounding).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchtrack.association.grid import DENSE_PAIRS
from torchtrack.filters.gmphd.filter import gated_pairs
from torchtrack.gaussian import (
    KalmanGain,
    gaussian_log_likelihood,
    log_det_from_cholesky,
)


def gated_candidates(z_hat: Tensor, S: Tensor, gain: KalmanGain, meas: Tensor, gate: float,
                     dense: bool | None = None) -> tuple[Tensor, Tensor]:
    """The gated candidates of each row: ``cand (N, K)`` measurement indices, each row's by decreasing
    log-likelihood, ``-1`` padding, and ``loglik (N, K)`` ``log N(z_j; ẑ_i, S_i)`` (``-inf`` padding;
    differentiable). ``z_hat (N, m)`` predicted measurements, ``S (N, m, m)`` their covariances, ``gain`` the
    Kalman factors of ``S`` (:func:`torchtrack.gaussian.kalman_gain`), ``meas (M, m)``, ``gate`` the NIS
    threshold. ``K``: the most candidates of a row. ``dense``: force the all-pairs (True) or the grid path
    (False); None: by size."""
    N, M = z_hat.shape[0], meas.shape[0]
    if dense is None:
        dense = N * M <= DENSE_PAIRS
    if dense:
        nis, loglik = _all_pairs_likelihood(z_hat, gain, meas)
        gated = nis.detach() <= gate
        K = int(gated.sum(1).max()) if N and M else 0
        vals, cand = torch.where(gated, loglik, torch.full_like(loglik, -math.inf)).topk(K, dim=1)
        return torch.where(torch.isfinite(vals.detach()), cand, torch.full_like(cand, -1)), vals
    ii, jj = gated_pairs(z_hat.detach(), S.detach(), gain.chol_inv.detach(), meas.detach(), gate,
                         torch.ones(N, dtype=torch.bool, device=meas.device), meas.shape[1])
    white = (gain.chol_inv.index_select(0, ii) * (meas.index_select(0, jj) - z_hat.index_select(0, ii))
             .unsqueeze(-2)).sum(-1)
    loglik = gaussian_log_likelihood(white.pow(2).sum(-1), log_det_from_cholesky(gain.chol).index_select(0, ii),
                                     meas.shape[1])
    # each row's pairs by decreasing likelihood (pairs come ordered by row), then their column in the table
    order = torch.argsort(loglik.detach(), descending=True, stable=True)
    order = order[torch.argsort(ii[order], stable=True)]
    ii, jj, loglik = ii[order], jj[order], loglik[order]
    count = torch.bincount(ii, minlength=N)
    K = int(count.max()) if ii.numel() else 0
    col = torch.arange(ii.shape[0], device=ii.device) - (torch.cumsum(count, 0) - count)[ii]
    cand = torch.full((N, K), -1, dtype=torch.long, device=meas.device)
    cand[ii, col] = jj
    vals = torch.full((N, K), -math.inf, dtype=loglik.dtype, device=meas.device).index_put((ii, col), loglik)
    return cand, vals


def _all_pairs_likelihood(z_hat: Tensor, gain: KalmanGain, meas: Tensor) -> tuple[Tensor, Tensor]:
    """NIS and ``log N(z_j; ẑ_i, S_i)`` of every pair ``(N, M)``: the whitening ``L⁻¹ ν`` (lower triangular)
    written out coordinate by coordinate over ``(N, M)`` planes — a batched GEMM of ``N`` tiny ``(M, m) × (m, m)``
    products costs several times more."""
    m = meas.shape[1]
    nu = [meas[:, k].unsqueeze(0) - z_hat[:, k].unsqueeze(1) for k in range(m)]          # m × (N, M)
    L_inv = gain.chol_inv.unsqueeze(1)                                                   # (N, 1, m, m)
    nis = None
    for k in range(m):
        white = L_inv[..., k, 0] * nu[0]
        for j in range(1, k + 1):
            white = white + L_inv[..., k, j] * nu[j]
        nis = white * white if nis is None else nis + white * white
    return nis, gaussian_log_likelihood(nis, log_det_from_cholesky(gain.chol).unsqueeze(-1), m)
