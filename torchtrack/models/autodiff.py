"""Batched Jacobians by autograd, for models that give none (used by the EKF)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor


def batched_jacobian(fn: Callable[[Tensor], Tensor], x: Tensor) -> Tensor:
    """``∂fn/∂x`` for ``x (*, n)`` and ``fn(x) (*, m)`` applied row-wise; returns ``(*, m, n)``.

    ``fn`` must treat rows independently. Differentiable (``create_graph`` semantics via
    ``torch.func``), so gradients flow through an EKF into model parameters.
    """
    batch = x.shape[:-1]
    flat = x.reshape(-1, x.shape[-1])
    jac = torch.func.vmap(torch.func.jacrev(lambda row: fn(row.unsqueeze(0)).squeeze(0)))(flat)
    return jac.reshape(*batch, jac.shape[-2], jac.shape[-1])
