"""Measurement models ``z = h(x) + v``, ``v ~ N(0, R)``.

Linear models expose :meth:`MeasurementModel.matrix` (``H``); nonlinear ones :meth:`measure` and
:meth:`jacobian` (by autograd where not given). :meth:`residual` is ``z − ẑ`` with angles wrapped.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.models.autodiff import batched_jacobian
from torchtrack.params import Covariance, Positive, as_float_tensor


class MeasurementModel(nn.Module):
    """Base class: ``meas_dim``, ``state_dim``, :meth:`noise_cov`, and ``matrix`` or ``measure``."""

    meas_dim: int
    state_dim: int
    is_linear: bool = True

    def matrix(self) -> Tensor:
        """``H (m, n)`` for linear models."""
        raise NotImplementedError(f"{type(self).__name__} is nonlinear: use measure()/jacobian()")

    def measure(self, x: Tensor) -> Tensor:
        """``h(x)``; ``x (*, n)`` → ``(*, m)``."""
        return (self.matrix() @ x.unsqueeze(-1)).squeeze(-1)

    def jacobian(self, x: Tensor) -> Tensor:
        """``∂h/∂x (*, m, n)``."""
        if self.is_linear:
            return self.matrix().expand(*x.shape[:-1], self.meas_dim, self.state_dim)
        return batched_jacobian(self.measure, x)

    def residual(self, z: Tensor, z_hat: Tensor) -> Tensor:
        return z - z_hat

    def noise_cov(self) -> Tensor:
        """``R (m, m)``."""
        raise NotImplementedError


class LinearMeasurement(MeasurementModel):
    """A general linear measurement with fixed ``H (m, n)`` and learnable ``R (m, m)`` (Covariance)."""

    def __init__(self, H, R, learnable: bool = True):
        super().__init__()
        H = as_float_tensor(H, "H")
        if H.dim() != 2:
            raise TorchtrackError(f"H must have shape (m, n); got {tuple(H.shape)}")
        self.meas_dim, self.state_dim = H.shape
        self.register_buffer("H", H)
        self.R = Covariance(torch.as_tensor(R, dtype=H.dtype), "measurement noise R", requires_grad=learnable)
        if self.R.raw.shape[-1] != self.meas_dim:
            raise TorchtrackError(f"R must be {self.meas_dim}x{self.meas_dim} like the rows of H")

    def matrix(self) -> Tensor:
        return self.H

    def noise_cov(self) -> Tensor:
        return self.R()


class LinearPosition(MeasurementModel):
    """Position of a ``[p (d), v (d), …]`` state: ``H = [I_d 0]``, ``R = diag(σ²)``.

    ``sigma`` is a scalar (isotropic) or one value per axis; learnable.
    """

    def __init__(self, ndim: int = 2, state_dim: int | None = None, sigma=1.0, learnable: bool = True):
        super().__init__()
        self.meas_dim = ndim
        self.state_dim = state_dim if state_dim is not None else 2 * ndim
        if self.state_dim < ndim:
            raise TorchtrackError(f"state_dim ({self.state_dim}) must be >= ndim ({ndim})")
        self.sigma = Positive(sigma, "measurement noise sigma", requires_grad=learnable)

    def matrix(self) -> Tensor:
        ref = self.sigma.raw
        return torch.eye(self.meas_dim, self.state_dim, dtype=ref.dtype, device=ref.device)

    def noise_cov(self) -> Tensor:
        return torch.diag_embed(self.sigma() ** 2 * self.sigma.raw.new_ones(self.meas_dim))


def wrap_angle(a: Tensor) -> Tensor:
    """Wrap to ``(−π, π]``."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


class RangeBearing(MeasurementModel):
    """Range and bearing from a sensor at ``sensor_position`` to a ``[x, y, …]`` state.

    ``z = [r, β]``, ``r = √(Δx² + Δy²)``, ``β = atan2(Δx, Δy)``: the bearing is measured **from the
    +y axis (north) clockwise towards +x (east)**, i.e. ``arctan(x/y)`` as in the JTC paper (eq. 2).
    ``sigma_range`` in metres, ``sigma_bearing`` in radians; both learnable.
    """

    is_linear = False

    def __init__(self, sensor_position=(0.0, 0.0), sigma_range: float = 1.0, sigma_bearing: float = 0.01,
                 state_dim: int = 4, learnable: bool = True):
        super().__init__()
        self.meas_dim = 2
        self.state_dim = state_dim
        self.register_buffer("sensor_position", torch.as_tensor(sensor_position, dtype=torch.get_default_dtype()))
        self.sigma_range = Positive(sigma_range, "range noise sigma_range", requires_grad=learnable)
        self.sigma_bearing = Positive(sigma_bearing, "bearing noise sigma_bearing", requires_grad=learnable)

    def measure(self, x: Tensor) -> Tensor:
        d = x[..., :2] - self.sensor_position.to(x)
        r = torch.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
        return torch.stack([r, torch.atan2(d[..., 0], d[..., 1])], -1)

    def jacobian(self, x: Tensor) -> Tensor:
        d = x[..., :2] - self.sensor_position.to(x)
        r2 = (d**2).sum(-1, keepdim=True).clamp_min(1e-12)
        J = torch.stack([d / r2.sqrt(), torch.stack([d[..., 1], -d[..., 0]], -1) / r2], -2)   # ∂(r, β)/∂(x, y)
        return nn.functional.pad(J, (0, self.state_dim - 2))

    def residual(self, z: Tensor, z_hat: Tensor) -> Tensor:
        nu = z - z_hat
        return torch.stack([nu[..., 0], wrap_angle(nu[..., 1])], -1)

    def noise_cov(self) -> Tensor:
        return torch.diag_embed(torch.stack([self.sigma_range() ** 2, self.sigma_bearing() ** 2]))


class RelativePosition(MeasurementModel):
    """A target's position measured relative to a sensor whose own state is uncertain (PMB paper).

    ``z = H_t x_t − H_s x_s + v``, ``v ~ N(0, R)``, with ``x_t`` a ``[p (d), v (d)]`` target state and
    ``x_s`` a ``[p (d), v (d)]`` sensor state. On the **joint** state ``[x_s, x_t]`` the model is
    linear with ``H = [−H_s, H_t]`` (:meth:`matrix`); :meth:`inflated_noise_cov` gives the variance-
    inflation approximation ``R + H_s Σ_s H_sᵀ``; :meth:`target_matrix` is ``H_t`` alone.
    """

    def __init__(self, ndim: int = 2, sigma=1.0, target_dim: int | None = None, sensor_dim: int | None = None,
                 learnable: bool = True):
        super().__init__()
        self.meas_dim = ndim
        self.target_dim = target_dim or 2 * ndim
        self.sensor_dim = sensor_dim or 2 * ndim
        self.state_dim = self.sensor_dim + self.target_dim
        self.sigma = Positive(sigma, "measurement noise sigma", requires_grad=learnable)

    def _position_matrix(self, n: int) -> Tensor:
        ref = self.sigma.raw
        return torch.eye(self.meas_dim, n, dtype=ref.dtype, device=ref.device)

    def target_matrix(self) -> Tensor:
        return self._position_matrix(self.target_dim)

    def sensor_matrix(self) -> Tensor:
        return self._position_matrix(self.sensor_dim)

    def matrix(self) -> Tensor:
        return torch.cat([-self.sensor_matrix(), self.target_matrix()], -1)

    def noise_cov(self) -> Tensor:
        ref = self.sigma.raw
        return self.sigma() ** 2 * torch.eye(self.meas_dim, dtype=ref.dtype, device=ref.device)

    def inflated_noise_cov(self, sensor_cov: Tensor) -> Tensor:
        """``R + H_s Σ_s H_sᵀ``; ``sensor_cov (*, n_s, n_s)`` → ``(*, m, m)``."""
        Hs = self.sensor_matrix()
        return self.noise_cov() + Hs @ sensor_cov @ Hs.transpose(-1, -2)
