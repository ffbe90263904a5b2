"""Marginal association probabilities by loopy belief propagation (Williams & Lau 2014).

The problem: ``n`` tracks and ``m`` measurements. Track ``i`` takes either *miss* (weight
``w_i0``) or one measurement ``j`` (weight ``w_ij``); measurement ``j`` comes from at most one
track, otherwise it is a new target or clutter (weight ``λ_j``). A joint association ``a`` has
weight ``Π_i w_{i,a(i)} · Π_{j unused} λ_j`` and we want the marginals ``p_i(j)``, ``p_i(0)`` and
``p_j(new)``.

Williams & Lau (2014) pass messages between track and measurement nodes. Dividing column ``j`` by
``λ_j`` and row ``i`` by any ``c_i > 0`` (the marginals are invariant to both) leaves the scaled
weights ``a_ij = w_ij / (c_i λ_j)``, ``a_i0 = w_i0 / c_i`` and the iteration::

    μ_ij = a_ij / (a_i0 + Σ_{j'≠j} a_ij' ν_j'i)      (track i → measurement j)
    ν_ji = 1 / (1 + Σ_{i'≠i} μ_i'j)                 (measurement j → track i)

started from ``ν = 1``; ``μ`` and ``ν`` do not depend on ``c_i``. (Williams & Lau take
``c_i = w_i0``, i.e. ``a_i0 = 1``; a zero miss weight then makes every ratio infinite.) Here ``c_i``
is the track's largest weight, ``c_i = max(w_i0, max_j w_ij / λ_j)``, taken in the log domain, so
every ``a ≤ 1``, the largest is 1, and the ratios between a track's options are kept exactly at
any magnitude. The marginals are::

    p_i(j) = a_ij ν_ji / t_i,   p_i(0) = a_i0 / t_i,   t_i = a_i0 + Σ_j' a_ij' ν_j'i
    p_j(i) = μ_ij / s_j,        p_j(new) = 1 / s_j,      s_j = 1 + Σ_i' μ_i'j

so rows ``(p_i(0), p_i(·))`` and columns ``(p_j(new), p_j(·))`` are distributions by
construction; at a fixed point ``p_i(j) = p_j(i)``. On a graph without cycles (no two tracks
competing for two measurements) the result is exact.

Each sum is formed once per pass and the sums "over all but one" come from it: ``t_i − a_ij ν_ji``
and ``s_j − μ_ij``. That subtraction loses the digits of a small remainder under one dominant
term (a track almost sure of one measurement), so the term that is more than half its sum — at
most one per row and per column — takes its remainder from a second sum without it
(:func:`_sum_of_others`); every other term is at most half the sum, which bounds the subtraction's
relative error by ``2 ε``. Because there is at most one such term per line, its position is the
product of the 0/1 comparison with the positions ``0, 1, …`` (a matrix-vector product, no host
synchronisation), and it is left out of the second sum by writing one zero per line (a scatter);
a line without one leaves out its first term, whose remainder is then exact as well. A pass is
therefore two reductions, one comparison, one matrix-vector product and two elementwise passes
over the ``n × m`` matrix (the cancelling version: one reduction, two elementwise passes), with no
loop over tracks; without autograd it writes into two preallocated buffers.

Weights come in the **log domain**; ``-inf`` marks a pair outside the gate, padding tracks have
all their ``w_ij = -inf`` and padding measurements all their ``w_ij = -inf`` (their outputs are
then ``p_i(0) = 1`` / ``p_j(new) = 1``). A zero new-target weight (``p_D = 1``, no clutter) is
raised to ``LOG_NEW_FLOOR[dtype]`` (twice the log of the smallest normal number: ``e^-1416`` in
float64, ``e^-175`` in float32), so that the scaled weights stay finite; a zero miss weight needs
nothing. A remainder that is exactly 0 (a track whose only option is one measurement) is raised
to the smallest normal number, so that ``μ`` stays finite.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.gaussian import scalar

LOG_NEW_FLOOR = {dt: 2.0 * float(torch.log(torch.tensor(torch.finfo(dt).tiny, dtype=torch.float64)))
                 for dt in (torch.float64, torch.float32, torch.float16, torch.bfloat16)}


class LBPResult(NamedTuple):
    """Marginals from :func:`lbp_marginals`; ``*`` is the batch shape."""

    assoc: Tensor      # (*, n, m) p_i(j), track side: rows with ``miss`` sum to one
    miss: Tensor       # (*, n)    p_i(0)
    new: Tensor        # (*, m)    p_j(new), measurement side: columns with ``meas_assoc`` sum to one
    meas_assoc: Tensor  # (*, n, m) p_j(i)
    iterations: int    # iterations run
    converged: bool    # max message change fell below ``tol`` (always False when ``tol`` is None)

    def assoc_matrix(self) -> Tensor:
        """``p_i(j)`` ``(*, n, m)`` (as :meth:`SparseLBPResult.assoc_matrix
        <torchtrack.association.lbp_sparse.SparseLBPResult.assoc_matrix>` gives the sparse result's)."""
        return self.assoc


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


def scaled_weights(log_w: Tensor, log_miss: Tensor, log_new: Tensor) -> tuple[Tensor, Tensor]:
    """``a_ij = w_ij / (c_i λ_j)`` ``(*, n, m)`` and ``a_i0 = w_i0 / c_i`` ``(*, n, 1)`` with
    ``c_i = max(w_i0, max_j w_ij / λ_j)`` (module docstring), batch dimensions broadcast.

    ``c_i`` is a constant for autograd (the marginals do not depend on it); a track with no finite
    weight at all gets ``a_i0 = 1`` (it misses).
    """
    log_new = log_new.clamp_min(LOG_NEW_FLOOR.get(log_new.dtype, LOG_NEW_FLOOR[torch.float32]))
    log_ratio = log_w - log_new.unsqueeze(-2)                                   # log(w_ij / λ_j), a new tensor
    with torch.no_grad():
        log_c = log_ratio.amax(-1) if log_ratio.shape[-1] else log_ratio.new_full(log_ratio.shape[:-1], float("-inf"))
        log_c = torch.maximum(log_miss, log_c)
        finite = torch.isfinite(log_c)
        log_c = torch.where(finite, log_c, torch.zeros_like(log_c))
    log_a0 = torch.where(finite, log_miss.expand_as(log_c) - log_c, torch.zeros_like(log_c))
    batch = log_c.shape[:-1]
    if torch.is_grad_enabled() and log_ratio.requires_grad:
        a = torch.exp(log_ratio - log_c.unsqueeze(-1))
    else:                                                       # in place: one buffer, two passes
        a = log_ratio.sub_(log_c.unsqueeze(-1)).exp_() if log_ratio.shape[:-2] == batch else \
            torch.exp(log_ratio - log_c.unsqueeze(-1))
    return a, torch.exp(log_a0).unsqueeze(-1)


def _positions(v: Tensor, dim: int) -> Tensor:
    """``0, 1, …`` along ``dim`` of ``v``, shaped for :func:`_top`: ``(m, 1)`` or ``(1, n)``; in ``v``'s
    dtype, at least float32 (whose integers are exact up to 2^24; float16's only up to 2048)."""
    positions = torch.arange(v.shape[dim], dtype=torch.promote_types(v.dtype, torch.float32), device=v.device)
    return positions.unsqueeze(-1) if dim == -1 else positions.unsqueeze(0)


def _top(above: Tensor, dim: int, positions: Tensor) -> Tensor:
    """Index along ``dim`` (kept) of the term above half its line's sum, 0 where there is none, from the
    0/1 comparison ``above``: at most one term per line is above half, so it is the product with
    ``positions`` (:func:`_positions`), one matrix-vector pass. (Two near-equal terms that both pass a
    rounded half give a sum of positions, clamped into range: any position serves such a line.)"""
    above = above.to(positions.dtype)
    return (above @ positions if dim == -1 else positions @ above).long().clamp_(max=positions.numel() - 1)


def _sum_of_others(v: Tensor, floor: Tensor | float, dim: int) -> tuple[Tensor, Tensor]:
    """``floor + Σ_{k≠j} v_k`` along ``dim`` for every ``j`` (``v ≥ 0``), and the full sum ``floor + Σ_k v_k``.

    One term per line, ``v_top`` (the one above half the sum, or else the first), is left out of a
    second sum: ``rest = floor + Σ_{k≠top} v_k`` is its remainder, while every other term's is
    ``total − v_j`` with ``v_j`` at most half the total, so the subtraction loses at most a factor 2
    of relative accuracy. ``rest`` is floored at the smallest normal number, so that every remainder
    is > 0 (a line whose sum is 0 has no feasible option). Differentiable (the position is a constant).
    """
    total = v.sum(dim, keepdim=True) + floor
    with torch.no_grad():
        top = _top(torch.gt(v, 0.5 * total).to(v.dtype), dim, _positions(v, dim))
    rest = (v.scatter(dim, top, 0.0).sum(dim, keepdim=True) + floor).clamp_min(torch.finfo(v.dtype).tiny)
    return (total - v).scatter(dim, top, rest), total


class _Lines(NamedTuple):
    """Constants of one direction for :func:`_others_inplace`, made once per call."""

    positions: Tensor   # :func:`_positions`
    zeros: Tensor       # zeros of the shape of a line index (what is written at the left-out term)
    floor: Tensor       # the floor: ``a_i0`` (rows) or 1 (columns)


def _lines(a: Tensor, dim: int, floor: Tensor) -> _Lines:
    zeros = a.new_zeros(a.shape[:-2] + ((a.shape[-2], 1) if dim == -1 else (1, a.shape[-1])))
    return _Lines(_positions(a, dim), zeros, floor)


def _others_inplace(v: Tensor, dim: int, out: Tensor, lines: _Lines) -> Tensor:
    """:func:`_sum_of_others` without autograd, into ``out``; ``v`` is overwritten (its left-out term
    zeroed). Returns the full sum. The rows' floor (the miss weights) may be 0, so their ``rest`` is
    floored; the columns' floor is 1. (Constants are tensors: a Python number costs a conversion per
    operation.)"""
    total = v.sum(dim, keepdim=True).add_(lines.floor)
    torch.gt(v, total * scalar(0.5, v), out=out)
    top = _top(out, dim, lines.positions)
    v.scatter_(dim, top, lines.zeros)
    rest = v.sum(dim, keepdim=True).add_(lines.floor)
    if dim == -1:
        rest.clamp_min_(torch.finfo(v.dtype).tiny)
    torch.sub(total, v, out=out)
    out.scatter_(dim, top, rest)
    return total


def _iterate(a: Tensor, a0: Tensor, iterations: int, tol: float | None, inplace: bool) -> tuple[Tensor, int, bool]:
    """``a_ij ν_ji`` after the iterations: differentiable (new tensors each pass), or with ``inplace`` in two
    buffers (no autograd; ``a`` contiguous)."""
    prod = a.clone() if inplace else a                              # ν = 1
    if inplace:
        mu = torch.empty_like(a)
        rows, cols = _lines(a, -1, a0), _lines(a, -2, scalar(1.0, a))
    last = None
    for it in range(1, iterations + 1):
        if inplace:
            t = _others_inplace(prod, -1, mu, rows)
            torch.div(a, mu, out=mu)
            s = _others_inplace(mu, -2, prod, cols)
            torch.div(a, prod, out=prod)
        else:
            others, t = _sum_of_others(prod, a0, -1)
            mu = a / others                                         # track → measurement
            others, s = _sum_of_others(mu, 1.0, -2)
            prod = a / others                                       # a_ij ν_ji, measurement → track
        if tol is not None and (it % 2 == 0 or it == iterations):
            stat = torch.cat([(a0 / t).flatten(), s.flatten().reciprocal()]).detach()
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
    a, a0 = scaled_weights(log_w, log_miss, log_new)
    a, a0 = a.expand(*batch, n, m), a0.expand(*batch, n, 1)
    tiny = torch.finfo(a.dtype).tiny
    if n == 0 or m == 0:                                            # nothing to associate
        return LBPResult(a, (a0 / a0.clamp_min(tiny)).squeeze(-1), a.new_ones(*batch, m), a, 0, True)
    if torch.is_grad_enabled() and (a.requires_grad or a0.requires_grad):
        prod, it, converged = _iterate(a, a0, iterations, tol, inplace=False)
        others, t = _sum_of_others(prod, a0, -1)
        mu = a / others                                             # μ from the final ν
        s = (mu.sum(-2, keepdim=True) + 1.0).clamp_min(tiny)
        return LBPResult(prod / t, (a0 / t).squeeze(-1), 1.0 / s.squeeze(-2), mu / s, it, converged)
    prod, it, converged = _iterate(a.contiguous(), a0, iterations, tol, inplace=True)
    t = (prod.sum(-1, keepdim=True) + a0).clamp_min_(tiny)
    assoc = prod / t
    mu = torch.empty_like(prod)
    _others_inplace(prod, -1, mu, _lines(prod, -1, a0))         # prod is overwritten
    torch.div(a, mu, out=mu)
    s = mu.sum(-2, keepdim=True).add_(1.0).clamp_min_(tiny)
    return LBPResult(assoc, (a0 / t).squeeze(-1), s.reciprocal().squeeze(-2), mu.div_(s), it, converged)
