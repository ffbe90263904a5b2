"""Motion (dynamic) models ``x_k = f(x_{k-1}, dt) + w_k``, ``w_k ~ N(0, Q(dt))``.

State layout: **positions first, then velocities (then accelerations)**, one block per derivative,
each block holding all spatial axes — ``[p_1 … p_d, v_1 … v_d]`` as in eq. (10) of the maneuver
paper. For two dimensions that is ``[x, y, vx, vy]``.

Every model is an ``nn.Module`` whose noise levels are learnable :mod:`torchtrack.params`.
``dt`` may be a float or a tensor of any batch shape; the returned matrices then carry that
batch shape ``(*dt.shape, n, n)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.models.autodiff import batched_jacobian
from torchtrack.params import Covariance, Positive, as_float_tensor


def as_dt(dt, like: Tensor) -> Tensor:
    """``dt`` as a tensor on ``like``'s dtype/device; raises unless every entry is > 0."""
    t = torch.as_tensor(dt, dtype=like.dtype, device=like.device)
    if not bool((t > 0).all()):
        raise TorchtrackError(f"dt must be > 0; got {dt!r}")
    return t


def _kron_eye(block: Tensor, d: int) -> Tensor:
    """``block ⊗ I_d`` for ``block (*, k, k)``: the per-axis matrix spread over ``d`` axes."""
    eye = torch.eye(d, dtype=block.dtype, device=block.device)
    k = block.shape[-1]
    out = block[..., :, None, :, None] * eye[:, None, :]
    return out.reshape(*block.shape[:-2], k * d, k * d)


def _matrix(rows: list[list[Tensor]]) -> Tensor:
    """The matrix ``(*, k, l)`` whose entries are the tensors ``rows[i][j]`` of shape ``*``."""
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def cv_transition(dt: Tensor, ndim: int) -> Tensor:
    """``[[1, dt], [0, 1]] ⊗ I_d``, shape ``(*dt.shape, 2d, 2d)``."""
    one = torch.ones_like(dt)
    return _kron_eye(_matrix([[one, dt], [0 * dt, one]]), ndim)


class MotionModel(nn.Module):
    """Base class. Subclasses define ``state_dim`` and :meth:`process_noise`, and either
    :meth:`transition_matrix` (linear models) or :meth:`transition` (nonlinear)."""

    state_dim: int
    is_linear: bool = True

    def _ref(self) -> Tensor:
        """The unconstrained value of the first noise parameter (a plain tensor while being tuned): the
        model's dtype and device."""
        return next(m.raw for m in self.modules() if hasattr(m, "raw"))

    def transition_matrix(self, dt) -> Tensor:
        """``F(dt)``, shape ``(*dt.shape, n, n)``."""
        raise NotImplementedError(f"{type(self).__name__} is nonlinear: use transition()/jacobian()")

    def process_noise(self, dt) -> Tensor:
        """``Q(dt)``, shape ``(*dt.shape, n, n)``."""
        raise NotImplementedError

    def transition(self, x: Tensor, dt) -> Tensor:
        """``f(x, dt)``; ``x (*, n)``."""
        F = self.transition_matrix(dt)
        return (F @ x.unsqueeze(-1)).squeeze(-1)

    def jacobian(self, x: Tensor, dt) -> Tensor:
        """``∂f/∂x`` at ``x``, shape ``(*, n, n)``: ``F`` (broadcast) for linear models, else by autograd."""
        if self.is_linear:
            return self.transition_matrix(dt)
        return batched_jacobian(lambda s: self.transition(s, dt), x)


class LinearMotion(MotionModel):
    """A general linear-Gaussian model with fixed ``F (n, n)`` and learnable ``Q (n, n)``
    (``Q`` is a :class:`~torchtrack.params.Covariance`; ``dt`` is accepted and ignored)."""

    def __init__(self, F, Q, learnable: bool = True):
        super().__init__()
        F = as_float_tensor(F, "F")
        if F.dim() != 2 or F.shape[0] != F.shape[1]:
            raise TorchtrackError(f"F must be square (n, n); got shape {tuple(F.shape)}")
        self.state_dim = F.shape[0]
        self.register_buffer("F", F)
        self.Q = Covariance(torch.as_tensor(Q, dtype=F.dtype), "process noise Q", requires_grad=learnable)
        if self.Q.raw.shape[-1] != self.state_dim:
            raise TorchtrackError(f"Q must be {self.state_dim}x{self.state_dim} like F")

    def transition_matrix(self, dt) -> Tensor:
        as_dt(dt, self._ref())
        return self.F

    def process_noise(self, dt) -> Tensor:
        as_dt(dt, self._ref())
        return self.Q()


class ConstantPosition(MotionModel):
    """A (nearly) stationary target, state ``[p (d)]``: ``F = I``, ``Q = q dt I`` (random walk with
    spectral density ``q``; a tiny ``q`` gives the random-constant model of §3.1 of the maneuver paper)."""

    def __init__(self, ndim: int = 2, q: float = 1e-9, learnable: bool = True):
        super().__init__()
        self.ndim = ndim
        self.state_dim = ndim
        self.q = Positive(q, "process noise q", requires_grad=learnable)

    def transition_matrix(self, dt) -> Tensor:
        dt = as_dt(dt, self._ref())
        return torch.eye(self.ndim, dtype=dt.dtype, device=dt.device).expand(*dt.shape, self.ndim, self.ndim)

    def process_noise(self, dt) -> Tensor:
        dt = as_dt(dt, self._ref())
        return (self.q() * dt)[..., None, None] * torch.eye(self.ndim, dtype=dt.dtype, device=dt.device)


class ConstantVelocity(MotionModel):
    """Nearly constant velocity in ``ndim`` spatial dimensions, state ``[p (d), v (d)]``.

    ``noise="cwna"`` (continuous white-noise acceleration with spectral density ``q``)::

        Q = q [[dt³/3, dt²/2], [dt²/2, dt]] ⊗ I_d

    ``noise="pwca"`` (piecewise-constant white acceleration with variance ``q``; eq. 8–9 of the
    maneuver paper)::

        Q = q [[dt⁴/4, dt³/2], [dt³/2, dt²]] ⊗ I_d
    """

    def __init__(self, ndim: int = 2, q: float = 1.0, noise: str = "cwna", learnable: bool = True):
        super().__init__()
        if ndim < 1:
            raise TorchtrackError(f"ndim must be >= 1; got {ndim}")
        if noise not in ("cwna", "pwca"):
            raise TorchtrackError(f"noise must be 'cwna' or 'pwca'; got {noise!r}")
        self.ndim = ndim
        self.state_dim = 2 * ndim
        self.noise = noise
        self.q = Positive(q, "process noise q", requires_grad=learnable)

    def transition_matrix(self, dt) -> Tensor:
        return cv_transition(as_dt(dt, self._ref()), self.ndim)

    def process_noise(self, dt) -> Tensor:
        dt = as_dt(dt, self._ref())
        if self.noise == "cwna":
            rows = [[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]
        else:
            rows = [[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]]
        return _kron_eye(self.q() * _matrix(rows), self.ndim)


class ConstantAcceleration(MotionModel):
    """Nearly constant acceleration, state ``[p, v, a]`` (each ``d`` axes).

    ``noise="cwnj"``: continuous white-noise jerk, spectral density ``q``;
    ``noise="pwcj"``: piecewise-constant jerk increment ``σ² g gᵀ``, ``g = [dt²/2, dt, 1]``
    (Bar-Shalom et al. 2001, §6.2.3 and §6.3.3).
    """

    def __init__(self, ndim: int = 2, q: float = 1.0, noise: str = "cwnj", learnable: bool = True):
        super().__init__()
        if noise not in ("cwnj", "pwcj"):
            raise TorchtrackError(f"noise must be 'cwnj' or 'pwcj'; got {noise!r}")
        self.ndim = ndim
        self.state_dim = 3 * ndim
        self.noise = noise
        self.q = Positive(q, "process noise q", requires_grad=learnable)

    def transition_matrix(self, dt) -> Tensor:
        dt = as_dt(dt, self._ref())
        one, zero = torch.ones_like(dt), torch.zeros_like(dt)
        return _kron_eye(_matrix([[one, dt, dt**2 / 2], [zero, one, dt], [zero, zero, one]]), self.ndim)

    def process_noise(self, dt) -> Tensor:
        dt = as_dt(dt, self._ref())
        if self.noise == "cwnj":
            block = _matrix([[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                             [dt**3 / 6, dt**2 / 2, dt]])
        else:
            g = torch.stack([dt**2 / 2, dt, torch.ones_like(dt)], -1)
            block = g.unsqueeze(-1) * g.unsqueeze(-2)
        return _kron_eye(self.q() * block, self.ndim)


def _turn_block(w: Tensor, dt: Tensor) -> Tensor:
    """Coordinated-turn transition for ``[x, y, vx, vy]`` at rate ``w`` (rad/s); safe at ``w → 0``."""
    wt = w * dt
    small = wt.abs() < 1e-6
    w_safe = torch.where(small, torch.ones_like(w), w)
    s = torch.where(small, dt - w**2 * dt**3 / 6, torch.sin(wt) / w_safe)
    c = torch.where(small, w * dt**2 / 2, (1 - torch.cos(wt)) / w_safe)
    cos, sin = torch.cos(wt), torch.sin(wt)
    one, zero = torch.ones_like(wt), torch.zeros_like(wt)
    return _matrix([[one, zero, s, -c], [zero, one, c, s], [zero, zero, cos, -sin], [zero, zero, sin, cos]])


def acceleration_gain(dt: Tensor, ndim: int = 2) -> Tensor:
    """``G = [[dt²/2 I], [dt I]] (*dt.shape, 2d, d)``, mapping a ``d``-axis acceleration into ``[p, v]``."""
    eye = torch.eye(ndim, dtype=dt.dtype, device=dt.device)
    return torch.cat([(dt**2 / 2)[..., None, None] * eye, dt[..., None, None] * eye], -2)


class CoordinatedTurn(MotionModel):
    """Coordinated turn with a known rate ``omega`` (rad/s, counter-clockwise positive), state
    ``[x, y, vx, vy]``; process noise ``σ_a² G Gᵀ`` with ``G`` the acceleration gain."""

    def __init__(self, omega: float, sigma_a: float = 1.0, learnable: bool = True):
        super().__init__()
        self.state_dim = 4
        self.register_buffer("omega", torch.as_tensor(float(omega)))
        self.sigma_a = Positive(sigma_a, "acceleration noise sigma_a", requires_grad=learnable)

    def transition_matrix(self, dt) -> Tensor:
        dt = as_dt(dt, self._ref())
        return _turn_block(self.omega.to(dt), dt)

    def process_noise(self, dt) -> Tensor:
        G = acceleration_gain(as_dt(dt, self._ref()))
        return self.sigma_a() ** 2 * (G @ G.transpose(-1, -2))


class CoordinatedTurnRate(MotionModel):
    """Coordinated turn with the rate in the state, ``[x, y, vx, vy, ω]`` (nonlinear).

    ``Q = blockdiag(σ_a² G Gᵀ, σ_ω² dt²)``.
    """

    is_linear = False

    def __init__(self, sigma_a: float = 1.0, sigma_omega: float = math.radians(1.0), learnable: bool = True):
        super().__init__()
        self.state_dim = 5
        self.sigma_a = Positive(sigma_a, "acceleration noise sigma_a", requires_grad=learnable)
        self.sigma_omega = Positive(sigma_omega, "turn-rate noise sigma_omega", requires_grad=learnable)

    def transition(self, x: Tensor, dt) -> Tensor:
        dt = as_dt(dt, x)
        A = _turn_block(x[..., 4], dt)
        kin = (A @ x[..., :4].unsqueeze(-1)).squeeze(-1)
        return torch.cat([kin, x[..., 4:5]], -1)

    def process_noise(self, dt) -> Tensor:
        dt = as_dt(dt, self._ref())
        G = acceleration_gain(dt)
        Q = nn.functional.pad(self.sigma_a() ** 2 * (G @ G.transpose(-1, -2)), (0, 1, 0, 1))
        return Q + nn.functional.pad(((self.sigma_omega() * dt) ** 2)[..., None, None], (4, 0, 4, 0))


class ModeControlInput(MotionModel):
    """Mode-dependent control input ``x_k = F x_{k-1} + G (u(m_k) + w_k)``, ``w_k ~ N(0, σ(m_k)² I)``.

    Used by the JTC particle-filter paper (eq. 1) and the gate paper's IMM: ``F`` and ``G`` are those
    of a ``d``-axis nearly-constant-velocity model (``G = [[dt²/2 I], [dt I]]``), ``u`` is one
    acceleration vector per mode (``controls (M, d)``) and ``sigma (M,)`` one noise level per mode.
    Methods take ``mode``, an integer tensor of any batch shape, selecting the rows.
    """

    def __init__(self, controls, sigma, learnable: bool = True):
        super().__init__()
        u = torch.as_tensor(controls, dtype=torch.get_default_dtype())
        if u.dim() != 2:
            raise TorchtrackError(f"controls must have shape (modes, ndim); got {tuple(u.shape)}")
        self.num_modes, self.ndim = u.shape
        self.state_dim = 2 * self.ndim
        self.register_buffer("controls", u)
        sig = torch.as_tensor(sigma, dtype=u.dtype).expand(self.num_modes).clone()
        self.sigma = Positive(sig, "mode process noise sigma", requires_grad=learnable)

    def transition_matrix(self, dt) -> Tensor:
        return cv_transition(as_dt(dt, self._ref()), self.ndim)

    def gain(self, dt) -> Tensor:
        """``G (*dt.shape, 2d, d)``."""
        return acceleration_gain(as_dt(dt, self._ref()), self.ndim)

    def process_noise(self, dt, mode: Tensor | None = None) -> Tensor:
        """``σ(m)² G Gᵀ``; without ``mode`` one matrix per mode, shape ``(M, *dt.shape, 2d, 2d)``."""
        G = self.gain(dt)
        GGt = G @ G.transpose(-1, -2)
        sig2 = self.sigma() ** 2
        if mode is None:
            return sig2.reshape(-1, *([1] * GGt.dim())) * GGt
        return sig2[mode][..., None, None] * GGt

    def transition(self, x: Tensor, dt, mode: Tensor | None = None) -> Tensor:
        """``F x`` plus, with ``mode``, the control offset ``G u(m)`` (``mode`` broadcast with ``dt``)."""
        out = super().transition(x, dt)
        if mode is not None:
            out = out + (self.gain(dt) @ self.controls[mode].unsqueeze(-1)).squeeze(-1)
        return out
