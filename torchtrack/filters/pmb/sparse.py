"""The TOMB/P update's track part on the gated (Bernoulli, measurement) pairs only.

:class:`~torchtrack.filters.pmb.filter.PMBFilter` with ``sparse=True`` forms the single-target hypotheses
``w_ij = r_i p_D N(z_j; H m_i, S_i)`` only for the pairs inside the gate ``ν_ijᵀ S_i⁻¹ ν_ij ≤ γ`` and runs the
association (:func:`~torchtrack.association.lbp_sparse.sparse_lbp_marginals`) and the track-oriented merge on
that edge list, so memory and time follow the pairs, not ``N × M``. The pairs are the GM-PHD's gating
(:func:`torchtrack.filters.gmphd.filter.gated_pairs`: candidates from the shared grid within a radius that misses no
pair inside the gate, then the exact gate); up to ``DENSE_PAIRS`` pairs every pair is tested at once instead
(fewer operations than the grid's). Unbatched states and 2-D measurements (the grid is planar).
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

from torchtrack.association.grid import DENSE_PAIRS
from torchtrack.filters.gmphd.filter import gated_pairs as gmphd_gated_pairs
from torchtrack.gaussian import (
    gaussian_log_likelihood,
    innovation_cov,
    innovation_pairs,
    innovations_nis,
    kalman_gain,
    log_det_from_cholesky,
    posterior_cov,
    whitened_sq_norms,
)


class GatedPairs(NamedTuple):
    """The single-target hypotheses of ``N`` Bernoullis inside the gate: ``E`` pairs."""

    row: Tensor         # (E,) Bernoulli
    col: Tensor         # (E,) measurement
    log_lik: Tensor     # (E,) log N(z_j; H m_i, S_i)
    innovation: Tensor  # (E, d) ν_ij = z_j − H m_i
    gain: Tensor        # (N, n, d) K_i
    cov: Tensor         # (N, n, n) Kalman-updated covariance P_i⁺ (the same for every z_j)


def gated_pairs(mean: Tensor, cov: Tensor, valid: Tensor, z: Tensor, zmask: Tensor, H: Tensor, R: Tensor,
                gate_d2: float) -> GatedPairs:
    """The pairs of a Bernoulli (``mean (N, n)``, ``cov (N, n, n)``, live where ``valid (N,)``) and a real
    measurement (``z (M, 2)`` where ``zmask (M,)``) inside the gate ``ν ᵀ S⁻¹ ν ≤ gate_d2``, ``S = H P Hᵀ + R``
    (``H (2, n)``, ``R (2, 2)``), with their log-likelihoods and innovations."""
    PHt, S = innovation_cov(cov, H, R)                                     # (N, n, d), (N, d, d)
    gain = kalman_gain(S, PHt, "PMB: innovation covariance (track)")
    z_hat = mean @ H.transpose(-1, -2)                                    # (N, d)
    if mean.shape[0] * z.shape[0] <= DENSE_PAIRS:      # every pair at once: fewer operations than the grid's
        nis_all = innovations_nis(gain.chol_inv, innovation_pairs(z, z_hat))           # (N, M)
        ii, jj = ((nis_all <= gate_d2) & valid.unsqueeze(1) & zmask.unsqueeze(0)).nonzero().unbind(1)
        nis = nis_all[ii, jj]
        nu = z.index_select(0, jj) - z_hat.index_select(0, ii)            # (E, d)
    else:
        meas = zmask.nonzero().squeeze(1)
        ii, jj = gmphd_gated_pairs(z_hat, S, gain.chol_inv, z[meas], gate_d2, valid, z.shape[-1])
        jj = meas[jj]
        nu = z[jj] - z_hat[ii]                                             # (E, d)
        nis = whitened_sq_norms(gain.chol_inv[ii], nu.unsqueeze(1))[-1].squeeze(-1)
    log_lik = gaussian_log_likelihood(nis, log_det_from_cholesky(gain.chol)[ii], z.shape[-1])
    return GatedPairs(ii, jj, log_lik, nu, gain.gain, posterior_cov(cov, gain))


class PairMoments(NamedTuple):
    """Per Bernoulli, the association-weighted moments of its innovations (the TOMB merge's inputs)."""

    detected: Tensor   # (N,)       Σ_j p_i(j)
    nu_bar: Tensor     # (N, d)     Σ_j p_i(j) ν_ij
    V: Tensor          # (N, d, d)  Σ_j p_i(j) ν_ij ν_ijᵀ


def pair_moments(row: Tensor, assoc: Tensor, innovation: Tensor, N: int) -> PairMoments:
    """:class:`PairMoments` of ``N`` Bernoullis from the pairs' rows ``(E,)``, marginals ``p_i(j) (E,)`` and
    innovations ``(E, d)`` (segment sums)."""
    d = innovation.shape[-1]
    weighted = assoc.unsqueeze(-1) * innovation
    return PairMoments(assoc.new_zeros(N).index_add(0, row, assoc),
                       assoc.new_zeros(N, d).index_add(0, row, weighted),
                       assoc.new_zeros(N, d, d).index_add(0, row, weighted.unsqueeze(-1) * innovation.unsqueeze(-2)))
