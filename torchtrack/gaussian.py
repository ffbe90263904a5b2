"""Batched Gaussian algebra through Cholesky factors.

Shapes follow ``torch.distributions``: vectors are ``(*batch, n)``, covariances ``(*batch, n, n)``,
and batch dimensions broadcast. Nothing here forms an explicit inverse.

Notation (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*,
ch. 5): predicted state ``x⁻, P⁻``; measurement ``z = H x + v``, ``v ~ N(0, R)``; innovation
``ν = z − H x⁻``; innovation covariance ``S = H P⁻ Hᵀ + R``; gain ``K = P⁻ Hᵀ S⁻¹``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError

LOG_2PI = math.log(2.0 * math.pi)


def symmetrize(P: Tensor) -> Tensor:
    """``(P + Pᵀ) / 2`` over the last two dimensions."""
    return 0.5 * (P + P.transpose(-1, -2))


# Below this size, many small factorisations and triangular solves are done as unrolled
# elementwise arithmetic over the batch (LAPACK's per-matrix call overhead dominates otherwise).
SMALL_N = 4
SMALL_BATCH = 64


def _is_small(A: Tensor, B: Tensor | None = None) -> bool:
    batch = A[..., 0, 0].numel() if B is None else max(A[..., 0, 0].numel(), B[..., 0, 0].numel())
    return A.shape[-1] <= SMALL_N and batch >= SMALL_BATCH


def _cholesky_unrolled(P: Tensor) -> tuple[Tensor, Tensor]:
    """Cholesky–Banachiewicz on ``(*, n, n)`` for small ``n``, elementwise over the batch."""
    n = P.shape[-1]
    L: list[list[Tensor | None]] = [[None] * n for _ in range(n)]
    ok = torch.ones(P.shape[:-2], dtype=torch.bool, device=P.device)
    for j in range(n):
        s = P[..., j, j]
        for k in range(j):
            s = s - L[j][k] ** 2
        ok = ok & (s > 0)
        d = torch.sqrt(torch.where(s > 0, s, torch.ones_like(s)))
        L[j][j] = d
        for i in range(j + 1, n):
            t = P[..., i, j]
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / d
    zero = torch.zeros_like(P[..., 0, 0])
    rows = [torch.stack([L[i][j] if j <= i else zero for j in range(n)], -1) for i in range(n)]
    return torch.stack(rows, -2), (~ok).to(torch.int32)


def _solve_lower_unrolled(L: Tensor, B: Tensor) -> Tensor:
    """Forward substitution ``L X = B`` for small ``n``; ``L (*, n, n)``, ``B (*, n, k)``."""
    n = L.shape[-1]
    X: list[Tensor] = []
    for i in range(n):
        t = B[..., i, :]
        for j in range(i):
            t = t - L[..., i, j, None] * X[j]
        X.append(t / L[..., i, i, None])
    return torch.stack(X, -2)


def _solve_upper_t_unrolled(L: Tensor, B: Tensor) -> Tensor:
    """Back substitution ``Lᵀ X = B`` for small ``n``."""
    n = L.shape[-1]
    X: list[Tensor | None] = [None] * n
    for i in reversed(range(n)):
        t = B[..., i, :]
        for j in range(i + 1, n):
            t = t - L[..., j, i, None] * X[j]
        X[i] = t / L[..., i, i, None]
    return torch.stack(X, -2)


def cholesky(P: Tensor, what: str = "covariance", check: bool = True) -> Tensor:
    """Lower Cholesky factor ``L`` with ``L Lᵀ = P``; shape ``(*batch, n, n)``.

    With ``check`` a failed factorisation raises :class:`TorchtrackError` naming ``what`` (one host
    synchronisation); without it a failed factor is left as returned by ``cholesky_ex``.
    """
    L, info = _cholesky_unrolled(P) if _is_small(P) else torch.linalg.cholesky_ex(P)
    if check and bool((info != 0).any()):
        bad = int((info != 0).sum())
        raise TorchtrackError(f"{what} is not positive definite ({bad} of {info.numel()} matrices failed "
                              "Cholesky factorisation)")
    return L


def solve_lower(L: Tensor, B: Tensor) -> Tensor:
    """``L⁻¹ B`` for lower-triangular ``L (*, n, n)`` and ``B (*, n, k)`` (batch dims broadcast)."""
    if _is_small(L, B):
        return _solve_lower_unrolled(L, B)
    return torch.linalg.solve_triangular(L, B, upper=False)


def chol_solve(L: Tensor, B: Tensor) -> Tensor:
    """``P⁻¹ B`` from the Cholesky factor ``L`` of ``P``; ``B (*, n, k)``."""
    if _is_small(L, B):
        return _solve_upper_t_unrolled(L, _solve_lower_unrolled(L, B))
    return torch.cholesky_solve(B, L)


def matmul(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` that runs a shared 2-D ``A (n, k)`` against a batch ``B (*, k, m)`` as one GEMM
    (``(Bᵀ Aᵀ)ᵀ``) instead of ``torch.matmul``'s expand-and-batch; otherwise plain ``@``."""
    if A.dim() == 2 and B.dim() > 2:
        return (B.transpose(-1, -2) @ A.transpose(0, 1)).transpose(-1, -2)
    return A @ B


def log_det_from_cholesky(L: Tensor) -> Tensor:
    """``log |P|`` from the Cholesky factor ``L`` of ``P``; shape ``(*batch,)``."""
    return 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)


def mahalanobis_sq(x: Tensor, mean: Tensor, L: Tensor) -> Tensor:
    """Squared Mahalanobis distance ``(x − μ)ᵀ P⁻¹ (x − μ)`` with ``L = chol(P)``.

    Shapes: ``x, mean (*, n)``, ``L (*, n, n)`` broadcast; result ``(*,)``.
    """
    diff = (x - mean).unsqueeze(-1)
    batch = torch.broadcast_shapes(diff.shape[:-2], L.shape[:-2])
    y = solve_lower(L.expand(*batch, *L.shape[-2:]), diff.expand(*batch, *diff.shape[-2:]))
    return y.squeeze(-1).pow(2).sum(-1)


def log_prob_from_cholesky(x: Tensor, mean: Tensor, L: Tensor) -> Tensor:
    """``log N(x; μ, P)`` with ``L = chol(P)``; broadcasting shapes as :func:`mahalanobis_sq`."""
    n = x.shape[-1]
    return -0.5 * (mahalanobis_sq(x, mean, L) + log_det_from_cholesky(L) + n * LOG_2PI)


def log_prob(x: Tensor, mean: Tensor, cov: Tensor) -> Tensor:
    """``log N(x; μ, Σ)``; ``x, mean (*, n)``, ``cov (*, n, n)``, broadcasting; result ``(*,)``."""
    return log_prob_from_cholesky(x, mean, cholesky(cov, "covariance"))


class KalmanUpdate(NamedTuple):
    """Result of :func:`kalman_update`; shapes for state size ``n`` and measurement size ``m``."""

    mean: Tensor          # (*, n) posterior mean x⁺
    cov: Tensor           # (*, n, n) posterior covariance P⁺ (Joseph form, symmetrised)
    innovation: Tensor    # (*, m) ν = z − ẑ
    innovation_cov: Tensor  # (*, m, m) S
    nis: Tensor           # (*,) normalised innovation squared νᵀ S⁻¹ ν
    log_likelihood: Tensor  # (*,) log N(ν; 0, S)
    gain: Tensor          # (*, n, m) K


def kalman_update(mean: Tensor, cov: Tensor, z: Tensor, H: Tensor, R: Tensor,
                  z_pred: Tensor | None = None, check: bool = True) -> KalmanUpdate:
    """Kalman measurement update through a Cholesky factor of ``S``.

    Equations (Bar-Shalom et al. 2001, eq. 5.2.3-9 … 5.2.3-15; Joseph form eq. 5.2.3-18)::

        ν = z − ẑ,  ẑ = H x⁻ (or ``z_pred`` for an EKF)
        S = H P⁻ Hᵀ + R
        K = P⁻ Hᵀ S⁻¹                       (solved, never inverted)
        x⁺ = x⁻ + K ν
        P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ

    Shapes: ``mean (*, n)``, ``cov (*, n, n)``, ``z (*, m)``, ``H (*, m, n)``, ``R (*, m, m)``; all
    batch dimensions broadcast.
    """
    z_hat = z_pred if z_pred is not None else (H @ mean.unsqueeze(-1)).squeeze(-1)
    nu = z - z_hat
    PHt = cov @ H.transpose(-1, -2)
    S = symmetrize(H @ PHt + R)
    L = cholesky(S, "innovation covariance S", check=check)
    # K = P Hᵀ S⁻¹  ⇔  S Kᵀ = H P
    K = chol_solve(L, PHt.transpose(-1, -2)).transpose(-1, -2)
    new_mean = mean + (K @ nu.unsqueeze(-1)).squeeze(-1)
    n = cov.shape[-1]
    I_KH = torch.eye(n, dtype=cov.dtype, device=cov.device) - K @ H
    new_cov = symmetrize(I_KH @ cov @ I_KH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2))
    white = solve_lower(L, nu.unsqueeze(-1)).squeeze(-1)
    nis = white.pow(2).sum(-1)
    m = nu.shape[-1]
    loglik = -0.5 * (nis + log_det_from_cholesky(L) + m * LOG_2PI)
    return KalmanUpdate(new_mean, new_cov, nu, S, nis, loglik, K)


def moment_match(log_weight: Tensor, mean: Tensor, cov: Tensor, dim: int = -1) -> tuple[Tensor, Tensor]:
    """Collapse a Gaussian mixture to one Gaussian with the same first two moments.

    ``μ = Σ wᵢ μᵢ``, ``Σ = Σ wᵢ (Σᵢ + (μᵢ − μ)(μᵢ − μ)ᵀ)`` with ``w = softmax(log_weight)``.

    Shapes: ``log_weight (*, K)``, ``mean (*, K, n)``, ``cov (*, K, n, n)`` with the mixture axis at
    ``dim`` of ``log_weight`` (the matching axis of ``mean``/``cov`` is ``dim-1``/``dim-2`` when
    ``dim`` is negative). Returns ``(*, n)`` and ``(*, n, n)``. Components with ``-inf`` log-weight
    are ignored.
    """
    if dim >= 0:
        dim = dim - log_weight.dim()
    w = torch.softmax(log_weight, dim=dim)
    mu = (w.unsqueeze(-1) * mean).sum(dim - 1)
    d = mean - mu.unsqueeze(dim - 1)
    spread = cov + d.unsqueeze(-1) * d.unsqueeze(-2)
    P = (w.unsqueeze(-1).unsqueeze(-1) * spread).sum(dim - 2)
    return mu, symmetrize(P)


def sample(mean: Tensor, cov: Tensor, generator: torch.Generator | None = None,
           sample_shape: tuple[int, ...] = ()) -> Tensor:
    """Draw ``x ~ N(μ, Σ)`` with shape ``(*sample_shape, *batch, n)``, reproducible via ``generator``."""
    L = cholesky(cov, "covariance")
    batch = torch.broadcast_shapes(mean.shape[:-1], L.shape[:-2])
    n = mean.shape[-1]
    eps = torch.randn((*sample_shape, *batch, n, 1), generator=generator, dtype=mean.dtype, device=mean.device)
    return mean + (L @ eps).squeeze(-1)


def check_covariance(P: Tensor, name: str, size: int | None = None) -> None:
    """Raise :class:`TorchtrackError` naming ``name`` unless ``P`` is square, symmetric, finite and PD."""
    if P.dim() < 2 or P.shape[-1] != P.shape[-2]:
        raise TorchtrackError(f"{name} must be square (*, n, n); got shape {tuple(P.shape)}")
    if size is not None and P.shape[-1] != size:
        raise TorchtrackError(f"{name} must be {size}x{size}; got {P.shape[-1]}x{P.shape[-1]}")
    if not bool(torch.isfinite(P).all()):
        raise TorchtrackError(f"{name} contains NaN or infinite entries")
    scale = P.abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1e-300)
    if not bool(((P - P.transpose(-1, -2)).abs() <= 1e-6 * scale).all()):
        raise TorchtrackError(f"{name} is not symmetric")
    cholesky(P, name)


def check_vector(x: Tensor, name: str, size: int) -> None:
    """Raise :class:`TorchtrackError` unless ``x`` has last dimension ``size``."""
    if x.dim() < 1 or x.shape[-1] != size:
        raise TorchtrackError(f"{name} must have shape (*, {size}); got {tuple(x.shape)}")
