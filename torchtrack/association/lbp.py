"""Marginal association probabilities by loopy belief propagation (Williams & Lau 2014).

The problem: ``n`` tracks and ``m`` measurements. Track ``i`` takes either *miss* (weight
``w_i0``) or one measurement ``j`` (weight ``w_ij``); measurement ``j`` comes from at most one
track, otherwise it is a new target or clutter (weight ``λ_j``). A joint association ``a`` has
weight ``Π_i w_{i,a(i)} · Π_{j unused} λ_j`` and we want the marginals ``p_i(j)``, ``p_i(0)`` and
``p_j(new)``.

Williams & Lau (2014) pass messages between track and measurement nodes. Dividing
row ``i`` by ``w_i0`` and column ``j`` by ``λ_j`` (the marginals are invariant to this) leaves one
ratio matrix ``ψ_ij = w_ij / (w_i0 λ_j)`` and the iteration::

    μ_ij = ψ_ij / (1 + Σ_{j'≠j} ψ_ij' ν_j'i)      (track i → measurement j)
    ν_ji = 1 / (1 + Σ_{i'≠i} μ_i'j)               (measurement j → track i)

started from ``ν = 1``. Each sum is formed once per iteration and the own term is subtracted
("total minus own"); the iteration carries ``ψ_ij ν_ji`` and ``μ_ij``, so it is four elementwise
passes and two reductions over the ``n × m`` matrix and no loop over tracks; without autograd the
passes write into two preallocated buffers. The marginals are::

    p_i(j) = ψ_ij ν_ji / (1 + Σ_j' ψ_ij' ν_j'i),  p_i(0) = 1 / (1 + Σ_j' ψ_ij' ν_j'i)
    p_j(i) = μ_ij / (1 + Σ_i' μ_i'j),             p_j(new) = 1 / (1 + Σ_i' μ_i'j)

so rows ``(p_i(0), p_i(·))`` and columns ``(p_j(new), p_j(·))`` are distributions by
construction; at a fixed point ``p_i(j) = p_j(i)``. On a graph without cycles (no two tracks
competing for one measurement) the result is exact.

Weights come in the **log domain**; ``-inf`` marks a pair outside the gate, padding tracks have
all their ``w_ij = -inf`` and padding measurements all their ``w_ij = -inf`` (their outputs are
then ``p_i(0) = 1`` / ``p_j(new) = 1``). ``log ψ`` is clamped above at ``LOG_RATIO_MAX[dtype]``
(25 in float64, 12 in float32), so that a zero miss or new-target weight (``p_D = 1``, no clutter)
gives finite messages, and so that "total minus own" cannot cancel below the floor of 1 that every
denominator has (the rounding error of the subtraction is about ``eps · ψ_max``: 1e-5 in float64,
2e-2 in float32, relative to that floor). The marginals then differ from the exact ones by at most
about ``e^{-LOG_RATIO_MAX}`` where the cap bites: a pair ``e^12`` times likelier than both its
alternatives is, to float32 accuracy, certain anyway.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError

LOG_RATIO_MAX = {torch.float64: 25.0, torch.float32: 12.0, torch.float16: 6.0, torch.bfloat16: 4.0}


class LBPResult(NamedTuple):
    """Marginals from :func:`lbp_marginals`; ``*`` is the batch shape."""

    assoc: Tensor      # (*, n, m) p_i(j), track side: rows with ``miss`` sum to one
    miss: Tensor       # (*, n)    p_i(0)
    new: Tensor        # (*, m)    p_j(new), measurement side: columns with ``meas_assoc`` sum to one
    meas_assoc: Tensor  # (*, n, m) p_j(i)
    iterations: int    # iterations run
    converged: bool    # max message change fell below ``tol`` (always False when ``tol`` is None)


def _check(log_w: Tensor, log_miss: Tensor, log_new: Tensor) -> None:
    if log_w.dim() < 2:
        raise TorchtrackError(f"lbp: log_w must be (*, n, m); got shape {tuple(log_w.shape)}")
    n, m = log_w.shape[-2:]
    if log_miss.shape[-1:] != (n,):
        raise TorchtrackError(f"lbp: log_miss must be (*, {n}); got shape {tuple(log_miss.shape)}")
    if log_new.shape[-1:] != (m,):
        raise TorchtrackError(f"lbp: log_new must be (*, {m}); got shape {tuple(log_new.shape)}")
    for name, t in (("log_w", log_w), ("log_miss", log_miss), ("log_new", log_new)):
        if bool(torch.isnan(t).any()) or bool((t == float("inf")).any()):
            raise TorchtrackError(f"lbp: {name} contains NaN or +inf")


def log_ratios(log_w: Tensor, log_miss: Tensor, log_new: Tensor) -> Tensor:
    """``ψ_ij = w_ij / (w_i0 λ_j)`` from log weights, clamped above at ``e^LOG_RATIO_MAX``; ``(*, n, m)``.

    A zero miss or new-target weight (``-inf``) is replaced by the most negative finite value first, so
    that a gated-out pair (``w_ij = 0``) stays at ``ψ = 0`` instead of ``exp(-inf + inf) = NaN`` and
    any other pair with it saturates at the cap. Without autograd the result is built in one buffer.
    """
    floor = torch.finfo(log_w.dtype).min / 4
    log_miss = log_miss.clamp_min(floor)
    log_new = log_new.clamp_min(floor)
    cap = LOG_RATIO_MAX.get(log_w.dtype, 12.0)
    if torch.is_grad_enabled() and (log_w.requires_grad or log_miss.requires_grad or log_new.requires_grad):
        return torch.exp((log_w - log_miss.unsqueeze(-1) - log_new.unsqueeze(-2)).clamp(max=cap))
    batch = torch.broadcast_shapes(log_w.shape[:-2], log_miss.shape[:-1], log_new.shape[:-1])
    out = torch.empty(*batch, *log_w.shape[-2:], dtype=log_w.dtype, device=log_w.device)
    torch.sub(log_w, log_miss.unsqueeze(-1), out=out)
    out.sub_(log_new.unsqueeze(-2)).clamp_(max=cap)
    return out.exp_()


def _iterate_functional(psi: Tensor, iterations: int, tol: float | None) -> tuple[Tensor, int, bool]:
    """``ψ_ij ν_ji`` after the iterations, differentiable (new tensors each pass)."""
    prod = psi                                                      # ν = 1
    last = None
    for it in range(1, iterations + 1):
        total = 1.0 + prod.sum(-1, keepdim=True)                    # 1 + Σ_j' ψ_ij' ν_j'i
        mu = psi / (total - prod)                                   # track → measurement
        col = 1.0 + mu.sum(-2, keepdim=True)                        # 1 + Σ_i' μ_i'j
        prod = psi / (col - mu)                                     # ψ_ij ν_ji, measurement → track
        if tol is not None and (it % 2 == 0 or it == iterations):
            stat = torch.cat([1.0 / total.flatten(), 1.0 / col.flatten()]).detach()
            if last is not None and (stat.numel() == 0 or float((stat - last).abs().amax()) < tol):
                return prod, it, True
            last = stat
    return prod, iterations, False


def _iterate_inplace(psi: Tensor, iterations: int, tol: float | None) -> tuple[Tensor, int, bool]:
    """The same iteration in two buffers (no autograd): four elementwise passes and two reductions."""
    prod = psi.clone()
    mu = torch.empty_like(psi)
    last = None
    for it in range(1, iterations + 1):
        total = prod.sum(-1, keepdim=True).add_(1.0)
        torch.sub(total, prod, out=mu)
        torch.div(psi, mu, out=mu)
        col = mu.sum(-2, keepdim=True).add_(1.0)
        torch.sub(col, mu, out=prod)
        torch.div(psi, prod, out=prod)
        if tol is not None and (it % 2 == 0 or it == iterations):
            stat = torch.cat([total.flatten().reciprocal(), col.flatten().reciprocal()])
            if last is not None and (stat.numel() == 0 or float((stat - last).abs().amax()) < tol):
                return prod, it, True
            last = stat
    return prod, iterations, False


def lbp_marginals(log_w: Tensor, log_miss: Tensor, log_new: Tensor, iterations: int = 50,
                  tol: float | None = 1e-7, check: bool = True) -> LBPResult:
    """Marginal association probabilities by loopy belief propagation.

    Args:
        log_w: ``(*, n, m)`` log weight of track ``i`` taking measurement ``j`` (``-inf``: not allowed).
        log_miss: ``(*, n)`` log weight of track ``i`` missing.
        log_new: ``(*, m)`` log weight of measurement ``j`` being a new target or clutter.
        iterations: iteration cap; with ``tol=None`` exactly this many iterations run (fixed mode,
            the one for autograd and for a fixed cost).
        tol: stop once no miss or new-target marginal ``p_i(0)``, ``p_j(new)`` changed by more than
            ``tol`` between two checks; checked every second iteration (one host synchronisation each).
        check: validate shapes and values (one synchronisation).

    Returns:
        :class:`LBPResult`. Batch dimensions of the three inputs broadcast; dtype follows ``log_w``.
        Gradients flow to all three inputs when autograd is on.
    """
    if check:
        _check(log_w, log_miss, log_new)
    if iterations < 1:
        raise TorchtrackError(f"lbp: iterations must be >= 1; got {iterations}")
    batch = torch.broadcast_shapes(log_w.shape[:-2], log_miss.shape[:-1], log_new.shape[:-1])
    n, m = log_w.shape[-2:]
    psi = log_ratios(log_w, log_miss, log_new).expand(*batch, n, m)
    if torch.is_grad_enabled() and psi.requires_grad:
        prod, it, converged = _iterate_functional(psi, iterations, tol)
        denom = 1.0 + prod.sum(-1, keepdim=True)
        assoc = prod / denom                                        # track side
        mu = psi / (denom - prod)                                   # μ from the final ν
        col = 1.0 + mu.sum(-2, keepdim=True)
        meas_assoc = mu / col                                       # measurement side
    else:
        prod, it, converged = _iterate_inplace(psi.contiguous(), iterations, tol)
        denom = prod.sum(-1, keepdim=True).add_(1.0)
        mu = torch.sub(denom, prod)
        torch.div(psi, mu, out=mu)
        col = mu.sum(-2, keepdim=True).add_(1.0)
        meas_assoc = mu.div_(col)
        assoc = prod.div_(denom)
    return LBPResult(assoc, 1.0 / denom.squeeze(-1), 1.0 / col.squeeze(-2), meas_assoc, it, converged)
