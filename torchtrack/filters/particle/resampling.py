"""Batched resampling of particle systems, and differentiable weights after resampling.

Every resampler maps log-weights ``(*B, N)`` (unnormalised, ``-inf`` allowed) to ancestor indices
``(*B, N)`` (``int64``) with ``E[#{i : a_i = j}] = N w_j`` where ``w = softmax(log_weight)``; all
rows of the batch are resampled at once, without Python loops over rows or particles.

* multinomial — ``a_i ~ Cat(w)`` i.i.d.;
* stratified  — ``a_i = F⁻¹((i + U_i)/N)``, ``U_i ~ U[0, 1)`` i.i.d.;
* systematic  — ``a_i = F⁻¹((i + U)/N)``, one ``U ~ U[0, 1)`` per row (computed in ``O(N)``);
* residual    — ``⌊N w_j⌋`` deterministic copies of each ``j``, the remaining ``N − Σ⌊N w_j⌋``
  drawn multinomially from the residual weights ``N w_j − ⌊N w_j⌋`` (Liu & Chen 1998).

``F⁻¹`` is the inverse of the cumulative weights, found by ``searchsorted``. Ancestor indices are
a discrete, stop-gradient selection. Gradients pass through resampling by the weights returned by
:func:`resampled_log_weight`:

* ``"stop-gradient"`` (default; Ścibior & Wood 2021, "Differentiable particle filtering without
  modifying the forward pass"): ``log w̃_i = log w_{a_i} − ⊥(log w_{a_i}) + ⊥(log w̄)`` with
  ``w̄ = (1/N) Σ_j w_j`` and ``⊥`` the stop-gradient. The forward values are the usual equal weights
  ``w̄``; the gradient of ``Σ_i w̃_i`` is ``w̄ Σ_i ∇ log w_{a_i}``, whose expectation is ``∇ Σ_j w_j``,
  so the gradient of the likelihood estimate stays unbiased at ``O(N)`` cost.
* ``"soft"`` (Karkus et al. 2018): ancestors drawn from ``q = α w + (1 − α)/N`` and
  ``w̃_i = w_{a_i} / q_{a_i}`` (rescaled to keep ``Σ w̃ ≈ Σ w``), differentiable in ``w``; ``α = 1`` is
  ordinary resampling without gradient through the selection, ``α = 0`` no selection pressure.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError


def normalized_log_weights(log_weight: Tensor) -> tuple[Tensor, Tensor]:
    """``log_softmax(log_weight, -1)`` and the ``logsumexp (*B, 1)`` taken out; a row whose weights are
    all ``-inf`` (degenerate) becomes uniform.

    This is the documented recovery from weight degeneracy: the particles are kept with equal
    weights rather than turning into NaN; the likelihood estimate of that row is ``-inf``.
    """
    lse = torch.logsumexp(log_weight, -1, keepdim=True)
    dead = torch.isneginf(lse)
    uniform = torch.full_like(log_weight, -math.log(log_weight.shape[-1]))
    return torch.where(dead, uniform, log_weight - torch.where(dead, 0.0, lse)), lse


def normalized_weights(log_weight: Tensor) -> Tensor:
    """``softmax(log_weight, -1)``, uniform for a degenerate row (:func:`normalized_log_weights`)."""
    return torch.exp(normalized_log_weights(log_weight)[0])


def _inverse_cdf(w: Tensor, u: Tensor) -> Tensor:
    """Indices ``j`` with ``F_{j-1} ≤ u < F_j`` for ``F = cumsum(w)``; ``w (*B, N)``, ``u (*B, K)`` in [0, 1)."""
    cdf = torch.cumsum(w, -1)
    idx = torch.searchsorted(cdf, u * cdf[..., -1:], right=True)
    return idx.clamp_max_(w.shape[-1] - 1)


def _uniform(shape, generator: torch.Generator | None, like: Tensor) -> Tensor:
    return torch.rand(shape, generator=generator, dtype=like.dtype, device=like.device)


def multinomial(log_weight: Tensor, generator: torch.Generator | None = None, num: int | None = None) -> Tensor:
    """``num`` (default ``N``) i.i.d. ancestors per row, by the inverse CDF of i.i.d. uniforms."""
    w = normalized_weights(log_weight)
    k = w.shape[-1] if num is None else num
    u = _uniform((*w.shape[:-1], k), generator, w)
    return _inverse_cdf(w, u)


def stratified(log_weight: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """One uniform per stratum ``[i/N, (i+1)/N)``."""
    w = normalized_weights(log_weight)
    n = w.shape[-1]
    i = torch.arange(n, dtype=w.dtype, device=w.device)
    return _inverse_cdf(w, (i + _uniform(w.shape, generator, w)) / n)


def systematic(log_weight: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """One uniform shared by all strata of a row; see :func:`systematic_from_uniform`."""
    w = normalized_weights(log_weight)
    return systematic_from_uniform(w, _uniform((*w.shape[:-1], 1), generator, w))


def systematic_from_uniform(weight: Tensor, u: Tensor) -> Tensor:
    """Systematic ancestors for non-negative weights ``(*B, N)`` (any positive total) and ``u (*B, 1)``.

    ``O(N)`` without a search: the grid points ``(i + u)/N`` below the cumulative weight ``F_j`` number
    ``e_j = ⌈N F_j / F_N − u⌉``, so slot ``i`` descends from ``a_i = #{j : e_j ≤ i}`` — a histogram of
    ``e`` and a cumulative sum. A row of zero weights must be handled by the caller.
    """
    n = weight.shape[-1]
    cdf = torch.cumsum(weight, -1)
    ends = torch.ceil(cdf * (n / cdf[..., -1:]) - u).clamp_(0, n).long()
    hist = torch.zeros((*ends.shape[:-1], n + 1), dtype=torch.long, device=ends.device)
    hist.scatter_add_(-1, ends, torch.ones((), dtype=ends.dtype, device=ends.device).expand_as(ends))
    return torch.cumsum(hist[..., :n], -1).clamp_max_(n - 1)


def residual(log_weight: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """``⌊N w⌋`` copies, then multinomial on the residuals for the remaining slots of each row."""
    w = normalized_weights(log_weight)
    n = w.shape[-1]
    nw = n * w
    copies = torch.floor(nw)
    ends = torch.cumsum(copies, -1)                      # slot k < ends_j belongs to particle ≤ j
    n_det = ends[..., -1:]
    slots = torch.arange(n, dtype=w.dtype, device=w.device).expand_as(w)
    det = torch.searchsorted(ends, slots.contiguous(), right=True).clamp_max_(n - 1)
    rest = (nw - copies).clamp_min(0)
    rest = torch.where(rest.sum(-1, keepdim=True) > 0, rest, torch.ones_like(rest))
    draws = _inverse_cdf(rest, _uniform(w.shape, generator, w))
    pos = (slots - n_det).clamp_min(0).long()
    return torch.where(slots < n_det, det, draws.gather(-1, pos))


RESAMPLERS: dict[str, Callable[[Tensor, torch.Generator | None], Tensor]] = {
    "multinomial": multinomial, "stratified": stratified, "systematic": systematic, "residual": residual,
}


def get_resampler(name: str) -> Callable[[Tensor, torch.Generator | None], Tensor]:
    """The resampler called ``name`` (one of :data:`RESAMPLERS`)."""
    if name not in RESAMPLERS:
        raise TorchtrackError(f"resampler must be one of {', '.join(RESAMPLERS)}; got {name!r}")
    return RESAMPLERS[name]


def offspring_counts(ancestors: Tensor, num_particles: int) -> Tensor:
    """How many times each particle was selected: ``(*B, N)`` counts from ancestors ``(*B, K)``."""
    counts = torch.zeros((*ancestors.shape[:-1], num_particles), dtype=torch.long, device=ancestors.device)
    return counts.scatter_add_(-1, ancestors, torch.ones_like(ancestors))


def resampled_log_weight(log_weight: Tensor, ancestors: Tensor, proposal_log_weight: Tensor | None = None) -> Tensor:
    """Log-weights after resampling with ancestors ``a``; shapes ``(*B, N)``.

    Without ``proposal_log_weight`` (ancestors drawn from ``w`` itself): the stop-gradient correction
    ``log w_{a_i} − ⊥(log w_{a_i}) + ⊥(log w̄)``. With it (soft resampling, ancestors drawn from the
    normalised ``q``): ``log ŵ_{a_i} − log q_{a_i} + log w̄`` where ``ŵ`` is the normalised ``w``.
    Both keep ``logsumexp`` of the weights equal to that before resampling (in expectation for soft).
    A degenerate row (all ``-inf``) stays at ``-inf``.
    """
    n = log_weight.shape[-1]
    lse = torch.logsumexp(log_weight, -1, keepdim=True)
    log_mean = lse - math.log(n)
    picked = log_weight.gather(-1, ancestors)
    if proposal_log_weight is None:
        finite = torch.isfinite(picked)
        corr = torch.where(finite, picked - picked.detach(), torch.zeros_like(picked))
        return corr + log_mean.detach()
    q = proposal_log_weight - torch.logsumexp(proposal_log_weight, -1, keepdim=True)
    lse_safe = torch.where(torch.isneginf(lse), torch.zeros_like(lse), lse)
    return picked - lse_safe - q.gather(-1, ancestors) + log_mean


def soft_proposal(log_weight: Tensor, alpha: float) -> Tensor:
    """``log q`` for ``q = α ŵ + (1 − α)/N`` (detached); ``log_weight (*B, N)``."""
    if not 0.0 <= alpha <= 1.0:
        raise TorchtrackError(f"soft resampling alpha must lie in [0, 1]; got {alpha}")
    w = normalized_weights(log_weight.detach())
    return torch.log(alpha * w + (1.0 - alpha) / w.shape[-1])
