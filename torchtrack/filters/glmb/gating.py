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
    innovation_pairs,
    innovations_likelihood,
    log_det_from_cholesky,
    whitened_sq_norms,
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
        nis, loglik = innovations_likelihood(gain, innovation_pairs(meas, z_hat))
        gated = nis.detach() <= gate
        K = int(gated.sum(1).max()) if N and M else 0
        vals, cand = torch.where(gated, loglik, torch.full_like(loglik, -math.inf)).topk(K, dim=1)
        return torch.where(torch.isfinite(vals.detach()), cand, torch.full_like(cand, -1)), vals
    ii, jj = gated_pairs(z_hat.detach(), S.detach(), gain.chol_inv.detach(), meas.detach(), gate,
                         torch.ones(N, dtype=torch.bool, device=meas.device), meas.shape[1])
    nu = meas.index_select(0, jj) - z_hat.index_select(0, ii)
    nis = whitened_sq_norms(gain.chol_inv.index_select(0, ii), nu.unsqueeze(1))
    loglik = gaussian_log_likelihood(nis[-1].squeeze(-1), log_det_from_cholesky(gain.chol).index_select(0, ii),
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
