"""The TOMB/P update's track part on the gated (Bernoulli, measurement) pairs only.

:class:`~torchtrack.filters.pmb.PMBFilter` with ``sparse=True`` forms the single-target hypotheses
``w_ij = r_i p_D N(z_j; H m_i, S_i)`` only for the pairs inside the gate ``ν_ijᵀ S_i⁻¹ ν_ij < γ`` and runs the
association (:func:`~torchtrack.association.lbp_sparse.sparse_lbp_marginals`) and the track-oriented merge on
that edge list, so memory and time follow the pairs, not ``N × M``. The candidates come from a grid of cells
(:func:`~torchtrack.association.grid.disc_candidates`) in measurement space with each Bernoulli's screening
radius ``√(γ tr S_i)``: ``νᵀ S⁻¹ ν ≥ ‖ν‖² / λ_max(S) ≥ ‖ν‖² / tr S``, so no pair inside the gate is missed, and
the exact gate is then applied to the candidates. Unbatched states and 2-D measurements (the grid is planar).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.association.grid import disc_candidates
from torchtrack.gaussian import (
    gaussian_log_likelihood,
    innovation_cov,
    kalman_gain,
    log_det_from_cholesky,
    posterior_cov,
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
    measurement (``z (M, 2)`` where ``zmask (M,)``) inside the gate ``ν ᵀ S⁻¹ ν < gate_d2``, ``S = H P Hᵀ + R``
    (``H (2, n)``, ``R (2, 2)``), with their log-likelihoods and innovations."""
    PHt, S = innovation_cov(cov, H, R)                                     # (N, n, d), (N, d, d)
    gain = kalman_gain(S, PHt, "PMB: innovation covariance (track)")
    z_hat = mean @ H.transpose(-1, -2)                                    # (N, d)
    radius = (gate_d2 * torch.diagonal(S, dim1=-2, dim2=-1).sum(-1)).sqrt() * (1 + 1e-6)
    tracks, meas = valid.nonzero().squeeze(1), zmask.nonzero().squeeze(1)
    ii, jj = disc_candidates(z_hat[tracks], radius[tracks], z[meas])
    ii, jj = tracks[ii], meas[jj]
    nu = z[jj] - z_hat[ii]                                                 # (C, d) candidates
    white = (gain.chol_inv[ii] @ nu.unsqueeze(-1)).squeeze(-1)
    nis = (white * white).sum(-1)
    inside = (nis < gate_d2).nonzero().squeeze(1)
    ii, jj, nu, nis = ii[inside], jj[inside], nu[inside], nis[inside]
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
