"""Probabilistic data association (PDA) update, batched over tracks (Bar-Shalom & Fortmann 1988, §6.4).

For a track with prediction ``x⁻, P⁻``, linear measurement model ``H, R`` (``S = H P⁻ Hᵀ + R``,
``K = P⁻ Hᵀ S⁻¹``) and the gated measurements ``z_j`` (innovations ``ν_j``)::

    L_j = p_D N(ν_j; 0, S) / λ                       (λ: clutter density)
    β_j = L_j / (1 − p_D p_G + Σ_l L_l),   β_0 = (1 − p_D p_G) / (1 − p_D p_G + Σ_l L_l)
    x⁺ = x⁻ + K ν,   ν = Σ_j β_j ν_j
    P⁺ = β_0 P⁻ + (1 − β_0) (P⁻ − K S Kᵀ) + K (Σ_j β_j ν_j ν_jᵀ − ν νᵀ) Kᵀ

which is the moment match of the mixture "no measurement is the target's" (weight ``β_0``) and
"``z_j`` is" (weight ``β_j``, the Kalman update with ``z_j``). Weights are computed in the log domain;
everything is differentiable.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.gaussian import GaussianState, innovation_cov, innovation_likelihood, kalman_gain, matmul, symmetrize


class PDAResult(NamedTuple):
    state: GaussianState   # (*, T, n), (*, T, n, n)
    weights: Tensor        # (*, T, 1 + Mz): β_0 (no detection) then β_j per measurement (0 outside the gate)
    log_likelihood: Tensor  # (*, T) log of the PDA normaliser relative to clutter, log(1 − p_D p_G + Σ L_j)


def pda_update(state: GaussianState, z: Tensor, gate_mask: Tensor, H: Tensor, R: Tensor, p_detect: float,
               clutter_density: Tensor | float, p_gate: float = 1.0) -> PDAResult:
    """PDA update of tracks ``state (*, T, n)`` with measurements ``z (*, Mz, m)``.

    ``gate_mask (*, T, Mz)`` marks the validated measurements of each track; ``H (m, n)``, ``R (m, m)``;
    ``clutter_density`` λ > 0 (scalar or ``(*, 1, 1)``-broadcastable); ``p_gate`` is the gate probability.
    """
    if not 0.0 < p_detect <= 1.0 or not 0.0 < p_gate <= 1.0:
        raise TorchtrackError(f"p_detect and p_gate must lie in (0, 1]; got {p_detect}, {p_gate}")
    lam = torch.as_tensor(clutter_density, dtype=z.dtype, device=z.device)
    if bool((lam <= 0).any()):
        raise TorchtrackError("clutter_density must be > 0")
    x, P = state.mean, state.cov
    PHt, S = innovation_cov(P, H, R)
    gain = kalman_gain(S, PHt, "PDA innovation covariance S")
    K = gain.gain                                                                  # (*, T, n, m)
    z_hat = matmul(H, x.unsqueeze(-1)).squeeze(-1)
    nu = z.unsqueeze(-3) - z_hat.unsqueeze(-2)                                    # (*, T, Mz, m)
    _, log_n = innovation_likelihood(gain.chol.unsqueeze(-3), nu)                 # log N(ν_j; 0, S)
    log_l = math.log(p_detect) + log_n - torch.log(lam)
    log_l = torch.where(gate_mask, log_l, torch.full_like(log_l, -math.inf))
    miss = 1.0 - p_detect * p_gate
    log_miss = torch.full_like(log_l[..., :1], math.log(miss) if miss > 0 else -math.inf)
    logits = torch.cat([log_miss, log_l], -1)
    norm = torch.logsumexp(logits, -1)
    beta = torch.exp(logits - norm.unsqueeze(-1))
    b0, bj = beta[..., 0], beta[..., 1:]
    nu_c = (bj.unsqueeze(-1) * nu).sum(-2)                                        # (*, T, m)
    mean = x + (K @ nu_c.unsqueeze(-1)).squeeze(-1)
    outer = (bj[..., None, None] * nu.unsqueeze(-1) * nu.unsqueeze(-2)).sum(-3)
    spread = outer - nu_c.unsqueeze(-1) * nu_c.unsqueeze(-2)
    W = gain.white_cross                                                          # K S Kᵀ = W Wᵀ
    cov = P - (1 - b0)[..., None, None] * (W @ W.transpose(-1, -2)) + K @ spread @ K.transpose(-1, -2)
    return PDAResult(GaussianState(mean, symmetrize(cov)), beta, norm)


__all__ = ["PDAResult", "pda_update"]
