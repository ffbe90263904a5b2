"""Differentiable losses for tuning.

The likelihood losses (Kalman / IMM marginal log-likelihood, particle-filter estimate, GM-PHD
predictive likelihood) are computed by the filters themselves; this module adds the truth-based
loss, a soft (entropic optimal-transport) GOSPA.

GOSPA (Rahmathullah, García-Fernández & Svensson 2017, α = 2) between an estimate set ``X`` and a
truth set ``Y`` with cut-off ``c`` and order ``p``::

    d(X, Y)^p = min_γ  Σ_{(i,j)∈γ} min(‖x_i − y_j‖, c)^p  +  c^p / 2 · (|X| + |Y| − 2|γ|)

is the optimal cost of a transport problem with a *dustbin* row and column (as in SuperGlue):
estimate ``i`` carries mass ``w_i`` (1 for a hard estimate; an existence weight for a soft one),
truth ``j`` mass 1, the dustbin row mass ``Σ_j 1`` (missed truths) and the dustbin column mass
``Σ_i w_i`` (false estimates); costs ``C_ij = min(‖x_i − y_j‖, c)^p``, ``c^p/2`` to a dustbin, 0
dustbin-to-dustbin. With 0/1 masses the transport polytope has integral vertices, so the linear
programme equals GOSPA^p exactly; the entropic version (Cuturi 2013)

    P_ε = argmin_P ⟨P, C⟩ − ε H(P)   (log-domain Sinkhorn, a fixed number of iterations)

returns ``⟨P_ε, C⟩``, which tends to GOSPA^p as ``ε → 0`` and is differentiable in the estimates,
their weights and everything upstream (filter parameters).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError


def sinkhorn_gospa(estimates: Tensor, truth: Tensor, est_weight: Tensor | None = None,
                   truth_mask: Tensor | None = None, c: float = 10.0, p: float = 2.0, eps: float = 0.05,
                   iters: int = 50) -> Tensor:
    """Soft GOSPA^p between estimate and truth sets, batched.

    Shapes: ``estimates (*, N, d)``, ``truth (*, M, d)``, ``est_weight (*, N)`` in [0, 1] (mass of
    each estimate; 0 for an empty slot; default 1), ``truth_mask (*, M)`` bool (default all present).
    ``eps`` is the entropic regularisation **relative to** ``c^p`` (dimensionless), ``iters`` the
    number of Sinkhorn iterations (log domain, differentiable by unrolling). Returns ``(*,)``, the
    transport cost ``⟨P, C⟩`` ≈ GOSPA^p (take the ``1/p`` power for the metric itself).
    """
    if estimates.shape[-1] != truth.shape[-1]:
        raise TorchtrackError(f"sinkhorn_gospa: estimates (*, N, {estimates.shape[-1]}) and truth "
                              f"(*, M, {truth.shape[-1]}) must have the same dimension")
    if c <= 0 or p < 1 or eps <= 0 or iters < 1:
        raise TorchtrackError(f"sinkhorn_gospa: need c > 0, p >= 1, eps > 0, iters >= 1; got c={c}, p={p}, "
                              f"eps={eps}, iters={iters}")
    dtype = torch.promote_types(estimates.dtype, truth.dtype)
    x, y = estimates.to(dtype), truth.to(dtype)
    batch = torch.broadcast_shapes(x.shape[:-2], y.shape[:-2])
    N, M = x.shape[-2], y.shape[-2]
    w = torch.ones(*x.shape[:-1], dtype=dtype, device=x.device) if est_weight is None else est_weight.to(dtype)
    v = (torch.ones(*y.shape[:-1], dtype=dtype, device=y.device) if truth_mask is None
         else truth_mask.to(dtype))
    w, v = w.expand(*batch, N), v.expand(*batch, M)
    cp = float(c) ** p
    diff = x.unsqueeze(-2) - y.unsqueeze(-3)                       # (*, N, M, d)
    # a smooth-at-zero distance so that gradients exist when an estimate sits on a truth point
    dist = (diff.pow(2).sum(-1) + torch.finfo(dtype).eps).sqrt()
    C = torch.minimum(dist.pow(p), torch.full_like(dist, cp)).expand(*batch, N, M)
    half = torch.full((*batch, N, 1), cp / 2, dtype=dtype, device=x.device)
    C = torch.cat([C, half], -1)                                   # dustbin column
    last = torch.cat([torch.full((*batch, 1, M), cp / 2, dtype=dtype, device=x.device),
                      torch.zeros(*batch, 1, 1, dtype=dtype, device=x.device)], -1)
    C = torch.cat([C, last], -2)                                   # (*, N+1, M+1)
    tiny = torch.finfo(dtype).tiny ** 0.5                          # empty slots: negligible, finite mass
    a = torch.cat([w, v.sum(-1, keepdim=True)], -1).clamp_min(tiny)
    b = torch.cat([v, w.sum(-1, keepdim=True)], -1).clamp_min(tiny)
    log_a, log_b = a.log(), b.log()
    e = eps * cp
    K = -C / e
    f = torch.zeros_like(log_a)
    g = torch.zeros_like(log_b)
    for _ in range(iters):
        f = log_a - torch.logsumexp(K + g.unsqueeze(-2), -1)
        g = log_b - torch.logsumexp(K + f.unsqueeze(-1), -2)
    P = torch.exp(K + f.unsqueeze(-1) + g.unsqueeze(-2))
    return (P * C).sum((-1, -2))

