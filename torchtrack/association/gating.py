"""Tracking gates (the gate paper): rectangular, ellipsoidal, class-conditioned, sample-based.

Every gate takes measurements ``z (*, Mz, m)`` (optional ``z_mask (*, Mz)``, ``True`` = real) and a
batch of ``T`` track predictions, and returns a :class:`Gate`: the tracks × measurements ``mask
(*, T, Mz)``, the gate ``volume (*, T)``, the gate statistic ``distance (*, T, Mz)`` (the paper's
performance index ξ, eq. 14; smaller is closer) and the ``threshold`` it was compared with.
``alpha`` is the probability that the true measurement falls outside (coverage ``1 − α``).

* Rectangular (eq. 1–2): ``|ν_i| / √S_ii ≤ γ`` for every axis, with the Bonferroni threshold
  ``γ = Φ⁻¹(1 − α / (2n))`` (two-sided per axis, so each axis misses with probability ``α/n`` and
  the coverage is ``≥ 1 − α``); volume ``Π_i 2 γ √S_ii``; ξ = ``max_i |ν_i| / √S_ii``.
* Ellipsoidal (eq. 4–6): ``νᵀ S⁻¹ ν ≤ γ``, ``γ = χ²_n⁻¹(1 − α)``; volume ``c_n γ^{n/2} |S|^{1/2}``,
  ``c_n = π^{n/2} / Γ(n/2 + 1)``; ξ = NIS.
* Highest-density gate from samples (eq. 18–21): draw ``N`` samples of the predicted measurement
  density ``p``, evaluate ``g = p(sample)``, take ``γ̂`` as the ``⌈αN⌉``-th smallest value; the gate is
  ``{z : p(z) ≥ γ̂}``. Its volume is estimated from the same samples by importance sampling,
  ``V ≈ (1/N) Σ 1{g ≥ γ̂} / g``; ξ = ``−log p(z)``. It only needs ``p`` up to a constant for
  the mask (the volume needs it normalised).
* Class-conditioned (eq. 28–32): the measurement prediction of class ``i`` is the Gaussian mixture
  ``Σ_j μ^{i,j} N(ẑ^{i,j}, S^{i,j})``; its gate is either the ellipse of the moment-matched
  Gaussian (eq. 31–32) or the exact mixture highest-density region (eq. 18–21 with this mixture).
* General nonlinear systems: :func:`nonlinear_gate` builds ``p(z) ≈ (1/P) Σ_p N(z; h(x_p), R)``
  from samples ``x_p`` of the predicted state and applies the sample-based gate.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.gaussian import LOG_2PI, chi2_quantile, cholesky, log_det_from_cholesky, moment_match


class Gate(NamedTuple):
    """A batch of gates: ``mask (*, T, Mz)``, ``volume (*, T)``, ``distance (*, T, Mz)``, ``threshold``."""

    mask: Tensor
    volume: Tensor
    distance: Tensor
    threshold: Tensor


def check_alpha(alpha: float) -> float:
    """``alpha`` as a float; raises :class:`TorchtrackError` unless ``0 < alpha < 1``."""
    a = float(alpha)
    if not 0.0 < a < 1.0:
        raise TorchtrackError(f"gate alpha (probability outside the gate) must lie in (0, 1); got {alpha!r}")
    return a


def rectangular_threshold(alpha: float, n: int) -> float:
    """Bonferroni per-axis threshold ``γ_{α/n} = Φ⁻¹(1 − α / (2n))`` (eq. 1–2)."""
    from scipy.stats import norm

    return float(norm.ppf(1.0 - check_alpha(alpha) / (2 * n)))


def ellipsoid_volume(threshold: Tensor | float, log_det: Tensor, n: int) -> Tensor:
    """Volume ``c_n γ^{n/2} |S|^{1/2}`` of ``{ν : νᵀ S⁻¹ ν ≤ γ}``; ``log_det = log |S|``."""
    c_n = math.pi ** (n / 2) / math.gamma(n / 2 + 1)
    t = torch.as_tensor(threshold, dtype=log_det.dtype, device=log_det.device)
    return c_n * t.pow(n / 2) * torch.exp(0.5 * log_det)


def _whitened_sq(points: Tensor, mean: Tensor, L: Tensor) -> Tensor:
    """``(x − μ_k)ᵀ Σ_k⁻¹ (x − μ_k)`` for points ``(*, P, m)`` and components ``mean (*, K, m)``,
    ``L = chol(Σ) (*, K, m, m)``: one triangular solve per component with all ``P`` points as
    right-hand sides. Result ``(*, K, P)``."""
    d = points.unsqueeze(-3) - mean.unsqueeze(-2)                        # (*, K, P, m)
    batch = torch.broadcast_shapes(d.shape[:-2], L.shape[:-2])
    y = torch.linalg.solve_triangular(L.expand(*batch, *L.shape[-2:]),
                                      d.transpose(-1, -2).expand(*batch, *d.shape[-1:], d.shape[-2]), upper=False)
    return y.pow(2).sum(-2)


def _apply_mask(mask: Tensor, z_mask: Tensor | None) -> Tensor:
    return mask if z_mask is None else mask & z_mask.to(torch.bool).unsqueeze(-2)


def _pairs(z: Tensor, z_hat: Tensor) -> Tensor:
    """Innovations ``ν (*, T, Mz, m)`` for ``z (*, Mz, m)`` and ``z_hat (*, T, m)``."""
    if z.shape[-1] != z_hat.shape[-1]:
        raise TorchtrackError(f"measurement size {z.shape[-1]} != predicted measurement size {z_hat.shape[-1]}")
    return z.unsqueeze(-3) - z_hat.unsqueeze(-2)


def rectangular_gate(z: Tensor, z_hat: Tensor, S: Tensor, alpha: float, z_mask: Tensor | None = None) -> Gate:
    """Rectangular gate (eq. 1–2); ``z_hat (*, T, m)``, ``S (*, T, m, m)`` (only ``diag S`` is used)."""
    n = z.shape[-1]
    gamma = rectangular_threshold(alpha, n)
    sd = torch.diagonal(S, dim1=-2, dim2=-1).sqrt()                     # (*, T, m)
    dist = (_pairs(z, z_hat).abs() / sd.unsqueeze(-2)).amax(-1)         # (*, T, Mz)
    volume = (2 * gamma * sd).prod(-1)
    thr = torch.tensor(gamma, dtype=z.dtype, device=z.device)
    return Gate(_apply_mask(dist <= gamma, z_mask), volume, dist, thr)


def ellipsoidal_gate(z: Tensor, z_hat: Tensor, S: Tensor, alpha: float | None = None,
                     z_mask: Tensor | None = None, threshold: Tensor | float | None = None) -> Gate:
    """Ellipsoidal gate (eq. 4–6). ``threshold`` overrides ``χ²_n⁻¹(1 − α)`` (e.g. a calibrated one, ``(*, T)``)."""
    n = z.shape[-1]
    if threshold is None:
        if alpha is None:
            raise TorchtrackError("ellipsoidal_gate needs alpha or threshold")
        threshold = chi2_quantile(1.0 - check_alpha(alpha), n)   # χ²_n⁻¹(1 − α), eq. 6
    L = cholesky(S, "gate innovation covariance S")
    nis = _whitened_sq(z, z_hat, L)                                      # (*, T, Mz)
    thr = torch.as_tensor(threshold, dtype=z.dtype, device=z.device)
    mask = nis <= (thr.unsqueeze(-1) if thr.dim() else thr)
    return Gate(_apply_mask(mask, z_mask), ellipsoid_volume(thr, log_det_from_cholesky(L), n), nis, thr)


def mixture_log_density(x: Tensor, log_weight: Tensor, mean: Tensor, cov: Tensor,
                        per_component: bool = False) -> Tensor:
    """``log Σ_k w_k N(x; μ_k, Σ_k)`` at points ``x (*, P, m)``; ``log_weight (*, K)`` (normalised here),
    ``mean (*, K, m)``, ``cov (*, K, m, m)`` or ``(m, m)``; result ``(*, P)`` (with ``per_component`` the
    unweighted ``log N(x; μ_k, Σ_k)``, ``(*, K, P)``)."""
    L = cholesky(cov, "mixture component covariance")
    d2 = _whitened_sq(x, mean, L)                                         # (*, K, P)
    m = x.shape[-1]
    comp = -0.5 * (d2 + log_det_from_cholesky(L).unsqueeze(-1) + m * LOG_2PI)
    if per_component:
        return comp
    logw = torch.log_softmax(log_weight, -1).unsqueeze(-1)
    return torch.logsumexp(comp + logw, -2)


def sample_mixture(log_weight: Tensor, mean: Tensor, cov: Tensor, num: int,
                   generator: torch.Generator | None = None, return_component: bool = False):
    """``num`` draws of a Gaussian mixture per batch element: result ``(*, num, m)`` (and, with
    ``return_component``, the drawn component indices ``(*, num)``)."""
    batch = torch.broadcast_shapes(log_weight.shape[:-1], mean.shape[:-2], cov.shape[:-3])
    K, m = mean.shape[-2], mean.shape[-1]
    probs = torch.softmax(log_weight, -1).expand(*batch, K).reshape(-1, K)
    comp = torch.multinomial(probs, num, replacement=True, generator=generator).reshape(*batch, num)
    L = cholesky(cov, "mixture component covariance").expand(*batch, K, m, m)
    mu = mean.expand(*batch, K, m)
    idx = comp.unsqueeze(-1)
    mu_s = torch.gather(mu, -2, idx.expand(*batch, num, m))
    L_s = torch.gather(L, -3, idx.unsqueeze(-1).expand(*batch, num, m, m))
    eps = torch.randn(*batch, num, m, generator=generator, dtype=mean.dtype, device=mean.device)
    z = mu_s + (L_s * eps.unsqueeze(-2)).sum(-1)             # L ε row by row (no tiny batched matmuls)
    return (z, comp) if return_component else z


def density_threshold(sample_log_density: Tensor, alpha: float) -> Tensor:
    """``log γ̂``: the ``⌈αN⌉``-th smallest of the samples' log densities ``(*, N)`` (eq. 20–21)."""
    N = sample_log_density.shape[-1]
    k = max(1, math.ceil(check_alpha(alpha) * N))
    return torch.kthvalue(sample_log_density, k, dim=-1).values


def density_gate(log_density_z: Tensor, sample_log_density: Tensor, alpha: float,
                 z_mask: Tensor | None = None) -> Gate:
    """Highest-density gate from densities already evaluated: ``log p`` at the measurements
    ``(*, T, Mz)`` and at ``N`` samples of ``p`` ``(*, T, N)``."""
    log_gamma = density_threshold(sample_log_density, alpha)                          # (*, T)
    inside = sample_log_density >= log_gamma.unsqueeze(-1)
    neg = torch.where(inside, -sample_log_density, torch.full_like(sample_log_density, -math.inf))
    volume = torch.exp(torch.logsumexp(neg, -1) - math.log(sample_log_density.shape[-1]))
    mask = log_density_z >= log_gamma.unsqueeze(-1)
    return Gate(_apply_mask(mask, z_mask), volume, -log_density_z, -log_gamma)


def sample_gate(z: Tensor, samples: Tensor, log_density, alpha: float, z_mask: Tensor | None = None) -> Gate:
    """Sample-based gate (eq. 18–21) for any predicted measurement density.

    ``samples (*, T, N, m)`` are draws of the density; ``log_density(points (*, T, P, m)) -> (*, T, P)``
    evaluates it (normalised, for the volume). ``z (*, Mz, m)``.
    """
    T = samples.shape[-3]
    zz = z.unsqueeze(-3).expand(*z.shape[:-2], T, *z.shape[-2:])
    return density_gate(log_density(zz), log_density(samples), alpha, z_mask)


def mixture_gate(z: Tensor, log_weight: Tensor, mean: Tensor, cov: Tensor, alpha: float,
                 num_samples: int = 2000, generator: torch.Generator | None = None,
                 z_mask: Tensor | None = None) -> Gate:
    """Exact highest-density region of a Gaussian-mixture prediction ``(*, T, K, ·)`` by eq. 18–21."""
    samples = sample_mixture(log_weight, mean, cov, num_samples, generator)
    return sample_gate(z, samples, lambda x: mixture_log_density(x, log_weight, mean, cov), alpha, z_mask)


def class_conditioned_gate(z: Tensor, log_weight: Tensor, mean: Tensor, cov: Tensor, alpha: float,
                           region: str = "ellipse", num_samples: int = 2000,
                           generator: torch.Generator | None = None, z_mask: Tensor | None = None) -> Gate:
    """Gate of the class-conditioned Gaussian-mixture measurement prediction (eq. 28–32).

    ``log_weight (*, T, K)`` = ``log μ^{i,j}_{k+1|k}``, ``mean (*, T, K, m)`` = ``ẑ^{i,j}``, ``cov (*, T, K, m, m)``
    = ``S^{i,j}``. ``region="ellipse"``: ellipsoidal gate of the moment-matched Gaussian (eq. 31–32);
    ``region="density"``: the mixture's own highest-density region (eq. 18–21).
    """
    if region == "ellipse":
        z_hat, S = moment_match(log_weight, mean, cov)
        return ellipsoidal_gate(z, z_hat, S, alpha, z_mask)
    if region == "density":
        return mixture_gate(z, log_weight, mean, cov, alpha, num_samples, generator, z_mask)
    raise TorchtrackError(f"class-conditioned gate region must be 'ellipse' or 'density'; got {region!r}")


def nonlinear_gate(z: Tensor, state_samples: Tensor, measurement, alpha: float, num_samples: int = 2000,
                   generator: torch.Generator | None = None, z_mask: Tensor | None = None) -> Gate:
    """Sample-based gate for a nonlinear measurement model from predicted-state samples ``(*, T, P, n)``.

    ``p(z) ≈ (1/P) Σ_p N(z; h(x_p), R)`` (an equal-weight mixture), then eq. 18–21. Residuals are taken
    in the measurement space as is, so keep angles away from the wrap-around.
    """
    means = measurement.measure(state_samples)                      # (*, T, P, m)
    R = measurement.noise_cov().to(means)
    log_w = torch.zeros(means.shape[:-1], dtype=means.dtype, device=means.device)
    return mixture_gate(z, log_w, means, R.expand(*means.shape, means.shape[-1]), alpha, num_samples, generator,
                        z_mask)


__all__ = [
    "Gate", "check_alpha", "class_conditioned_gate", "density_gate", "density_threshold",
    "ellipsoid_volume", "ellipsoidal_gate", "mixture_gate", "mixture_log_density", "nonlinear_gate",
    "rectangular_gate", "rectangular_threshold", "sample_gate", "sample_mixture",
]
