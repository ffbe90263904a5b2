"""Constrained learnable parameters.

Each class stores an unconstrained ``nn.Parameter`` and returns the constrained value when called:

=========================  =============================================  ===========================
class                      transform                                      use
=========================  =============================================  ===========================
:class:`Positive`          ``softplus(θ)`` (+ floor)                      standard deviations, rates
:class:`Probability`       ``sigmoid(θ)``                                 p_D, p_S, existence
:class:`RowStochastic`     ``softmax(Θ, dim=-1)``                         Markov transition matrices
:class:`Covariance`        ``L Lᵀ``, ``L`` lower, ``diag(L) = softplus``  full covariances
=========================  =============================================  ===========================

``requires_grad=False`` freezes a parameter (it stays a buffer-like ``nn.Parameter``).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError


def as_float_tensor(value, name: str) -> Tensor:
    """``value`` as a tensor (floating point; integers become the default dtype), which must be finite."""
    t = torch.as_tensor(value)
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    if not bool(torch.isfinite(t).all()):
        raise TorchtrackError(f"{name} must be finite; got {value!r}")
    return t


def inverse_softplus(y: Tensor) -> Tensor:
    """``θ`` with ``softplus(θ) = y`` (stable for large ``y``)."""
    return y + torch.log(-torch.expm1(-y))


class _Constrained(nn.Module):
    """An unconstrained learnable ``raw``; ``name`` names the parameter in messages."""

    def __init__(self, raw: Tensor, name: str, requires_grad: bool):
        super().__init__()
        self.name = name
        self.raw = nn.Parameter(raw, requires_grad=requires_grad)


class Positive(_Constrained):
    """A positive tensor ``softplus(θ) + floor``; initial ``value`` must be > ``floor``."""

    def __init__(self, value, name: str = "value", floor: float = 0.0, requires_grad: bool = True):
        t = as_float_tensor(value, name)
        if not bool((t > floor).all()):
            raise TorchtrackError(f"{name} must be > {floor}; got {value!r}")
        super().__init__(inverse_softplus(t - floor), name, requires_grad)
        self.floor = floor

    def forward(self) -> Tensor:
        return nn.functional.softplus(self.raw) + self.floor


class Probability(_Constrained):
    """A probability ``sigmoid(θ)`` in (0, 1); ``value`` must lie strictly inside."""

    def __init__(self, value, name: str = "probability", requires_grad: bool = True):
        t = as_float_tensor(value, name)
        if not bool(((t > 0) & (t < 1)).all()):
            raise TorchtrackError(f"{name} must lie strictly between 0 and 1; got {value!r}")
        super().__init__(torch.logit(t), name, requires_grad)

    def forward(self) -> Tensor:
        return torch.sigmoid(self.raw)


class RowStochastic(_Constrained):
    """A row-stochastic matrix ``softmax(Θ, -1)``; ``value (*, K, K)`` with positive rows summing to 1."""

    def __init__(self, value, name: str = "transition matrix", requires_grad: bool = True, atol: float = 1e-6):
        t = as_float_tensor(value, name)
        if t.dim() < 2 or t.shape[-1] != t.shape[-2]:
            raise TorchtrackError(f"{name} must be square (*, K, K); got shape {tuple(t.shape)}")
        if not bool((t > 0).all()):
            raise TorchtrackError(f"{name} must have strictly positive entries (use a small value for "
                                  "'impossible' transitions)")
        sums = t.sum(-1)
        if not bool(((sums - 1).abs() <= atol).all()):
            raise TorchtrackError(f"rows of {name} must sum to 1; got row sums {sums.tolist()}")
        super().__init__(torch.log(t), name, requires_grad)

    def forward(self) -> Tensor:
        return torch.softmax(self.raw, dim=-1)


class Covariance(_Constrained):
    """A full covariance ``L Lᵀ`` with ``L`` lower triangular and ``diag(L) = softplus(·)``."""

    def __init__(self, value, name: str = "covariance", requires_grad: bool = True):
        t = as_float_tensor(value, name)
        if t.dim() < 2 or t.shape[-1] != t.shape[-2]:
            raise TorchtrackError(f"{name} must be square (*, n, n); got shape {tuple(t.shape)}")
        if not bool(torch.allclose(t, t.transpose(-1, -2), atol=1e-9, rtol=1e-6)):
            raise TorchtrackError(f"{name} must be symmetric")
        L, info = torch.linalg.cholesky_ex(t)
        if bool((info != 0).any()):
            raise TorchtrackError(f"{name} must be positive definite")
        raw = torch.tril(L, -1) + torch.diag_embed(inverse_softplus(torch.diagonal(L, dim1=-2, dim2=-1)))
        super().__init__(raw, name, requires_grad)

    def cholesky(self) -> Tensor:
        """The lower factor ``L``."""
        diag = nn.functional.softplus(torch.diagonal(self.raw, dim1=-2, dim2=-1))
        return torch.tril(self.raw, diagonal=-1) + torch.diag_embed(diag)

    def forward(self) -> Tensor:
        L = self.cholesky()
        return L @ L.transpose(-1, -2)
