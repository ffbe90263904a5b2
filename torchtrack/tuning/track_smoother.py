"""Batched constant-velocity Kalman filter and Rauch–Tung–Striebel smoother over many tracks with missing
measurements, and the leave-one-out predictive of each measurement (used by :mod:`torchtrack.tuning.calibrate`).

State ``[x, y, vx, vy]``, one frame per step, CWNA process noise of spectral density ``q``
(Bar-Shalom et al. 2001, eq. 6.2.2-12). The measurement is the position (``H = [I 0]``) or, with velocities,
the whole state (``H = I``; the detector's velocity is the target's), noise ``R = diag(σ², σ², σ_v², σ_v²)``.
Tracks are rows of a ``(B, T, m)`` array, NaN where a frame has no measurement; a track's first measurement
is taken under a diffuse prior, and the log-likelihood is that of the rest given it (eq. 5.2.6-3).

The leave-one-out predictive of a measurement ``z_k`` given all the others, ``N(z; μ, C)``, follows from the
smoothed posterior without refiltering: with ``S_s = R − H P_s Hᵀ`` and ``e = z − H m_s``,
``C = R S_s⁻¹ R`` and ``z − μ = R S_s⁻¹ e`` (Gaussian conditioning read backwards).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.gaussian import symmetrize

DIFFUSE = 1e6
"""Prior variance of every state entry before a track's first measurement (px², px²/frame²)."""


class Smoothed(NamedTuple):
    """Per track and frame: the smoothed mean ``(B, T, 4)`` and covariance ``(B, T, 4, 4)``; the leave-one-out
    predictive mean ``(B, T, m)`` and its state part ``A = C − R`` ``(B, T, m, m)`` (at frames without a
    measurement, ``H m_s`` and ``H P_s Hᵀ``); the log-likelihood ``(B,)`` of each track's measurements after
    its first."""

    mean: Tensor
    cov: Tensor
    loo_mean: Tensor
    loo_state_cov: Tensor
    log_likelihood: Tensor


def cv_matrices(q: Tensor | float, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``F`` and ``Q`` of the 2-D CV model for one frame (eq. 6.2.2-12); ``q`` a number or ``(B,)`` (one ``Q``
    per track)."""
    eye = torch.eye(2, dtype=dtype)
    zero = torch.zeros(2, 2, dtype=dtype)
    F = torch.cat([torch.cat([eye, eye], 1), torch.cat([zero, eye], 1)], 0)
    q = torch.as_tensor(q, dtype=dtype)
    Q = q.reshape(q.shape + (1, 1)) * torch.cat([torch.cat([eye / 3, eye / 2], 1), torch.cat([eye / 2, eye], 1)], 0)
    return F, Q


def _noise(sigma: float, velocity_sigma: float | None, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    if velocity_sigma is None:
        return torch.cat([torch.eye(2, dtype=dtype), torch.zeros(2, 2, dtype=dtype)], 1), \
            torch.eye(2, dtype=dtype) * sigma ** 2
    return torch.eye(4, dtype=dtype), torch.diag(torch.tensor([sigma ** 2] * 2 + [velocity_sigma ** 2] * 2,
                                                              dtype=dtype))


def _update(m: Tensor, P: Tensor, z: Tensor, seen: Tensor, H: Tensor, R: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    S = symmetrize(H @ P @ H.T + R)
    L = torch.linalg.cholesky(S)
    e = torch.where(seen[:, None], z - m @ H.T, 0.0)
    K = torch.cholesky_solve(H @ P, L).transpose(-1, -2)                  # P Hᵀ S⁻¹
    I_KH = torch.eye(4, dtype=m.dtype) - K @ H
    P_new = symmetrize(I_KH @ P @ I_KH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2))   # Joseph form
    m_new = m + (K @ e.unsqueeze(-1)).squeeze(-1)
    nis = (e.unsqueeze(-2) @ torch.cholesky_solve(e.unsqueeze(-1), L)).squeeze(-1).squeeze(-1)
    ll = -0.5 * (nis + 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
                 + e.shape[-1] * torch.log(torch.tensor(2 * torch.pi, dtype=m.dtype)))
    keep = seen[:, None]
    return torch.where(keep, m_new, m), torch.where(keep[..., None], P_new, P), torch.where(seen, ll, 0.0)


def q_profile(z: Tensor, grid: Tensor, sigma: float, velocity_sigma: float | None = None) -> Tensor:
    """The log-likelihood ``(G, B)`` of each track ``z (B, T, m)`` at each process noise of ``grid (G,)``, all in
    one batched pass."""
    G, B = grid.shape[0], z.shape[0]
    ll = smooth(z.repeat(G, 1, 1), grid.repeat_interleave(B), sigma, velocity_sigma, backward=False).log_likelihood
    return ll.reshape(G, B)


def smooth(z: Tensor, q: Tensor | float, sigma: float, velocity_sigma: float | None = None,
           backward: bool = True) -> Smoothed:
    """Filter and (with ``backward``) smooth tracks ``z (B, T, m)`` (NaN rows: no measurement; m = 2 positions
    or 4 with velocities) with process noise ``q`` (a number or one per track, ``(B,)``); the first measurement
    of each track must be at ``t = 0``."""
    dtype = z.dtype
    B, T, m_dim = z.shape
    H, R = _noise(sigma, velocity_sigma if m_dim == 4 else None, dtype)
    F, Q = cv_matrices(q, dtype)
    seen = ~torch.isnan(z).any(-1)
    zz = torch.nan_to_num(z)
    m = torch.zeros(B, 4, dtype=dtype)
    P = torch.eye(4, dtype=dtype).expand(B, 4, 4) * DIFFUSE
    means, covs, pred_means, pred_covs = [], [], [], []
    ll = torch.zeros(B, dtype=dtype)
    for t in range(T):
        if t:
            m, P = m @ F.T, symmetrize(F @ P @ F.T + Q)
        pred_means.append(m)
        pred_covs.append(P)
        m, P, step_ll = _update(m, P, zz[:, t], seen[:, t], H, R)
        if t:
            ll = ll + step_ll
        means.append(m)
        covs.append(P)
    mean, cov = torch.stack(means, 1), torch.stack(covs, 1)
    if backward:
        ms, Ps = means[-1], covs[-1]
        out_m, out_P = [ms], [Ps]
        for t in range(T - 2, -1, -1):
            Lp = torch.linalg.cholesky(pred_covs[t + 1])
            G = torch.cholesky_solve(F @ covs[t], Lp).transpose(-1, -2)     # P_f Fᵀ P_pred⁻¹
            ms = means[t] + (G @ (ms - pred_means[t + 1]).unsqueeze(-1)).squeeze(-1)
            Ps = symmetrize(covs[t] + G @ (Ps - pred_covs[t + 1]) @ G.transpose(-1, -2))
            out_m.append(ms)
            out_P.append(Ps)
        mean, cov = torch.stack(out_m[::-1], 1), torch.stack(out_P[::-1], 1)
    hm = mean @ H.T
    hph = symmetrize(H @ cov @ H.T)
    Ss = symmetrize(R - hph)
    eye = torch.eye(m_dim, dtype=dtype)
    Ls, info = torch.linalg.cholesky_ex(torch.where(seen[..., None, None], Ss, eye))
    ok = seen & (info == 0)
    RSinv = torch.cholesky_solve(R.expand_as(Ss), Ls).transpose(-1, -2)   # R S_s⁻¹
    e = zz - hm
    loo_mean = torch.where(ok[..., None], zz - (RSinv @ e.unsqueeze(-1)).squeeze(-1), hm)
    loo_state = torch.where(ok[..., None, None], symmetrize(RSinv @ R) - R, hph)
    # a detection that alone fixes part of the state (S_s near singular) leaves rounding in A: keep A PSD
    evals, evecs = torch.linalg.eigh(symmetrize(loo_state))
    loo_state = symmetrize((evecs * evals.clamp(0.0, DIFFUSE).unsqueeze(-2)) @ evecs.transpose(-1, -2))
    return Smoothed(mean, cov, loo_mean, loo_state, ll)
