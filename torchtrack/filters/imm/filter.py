"""Interacting multiple model (IMM) filter, batched over any batch shape (tracks × runs × …).

Blom & Bar-Shalom (1988); Bar-Shalom, Li & Kirubarajan (2001) §11.6.6; the gate paper eq. 24–29.
With ``M`` model-matched filters sharing one state layout and a row-stochastic mode transition
matrix ``p_ij = Pr{m_k = j | m_{k-1} = i}`` (eq. 24), one cycle is::

    interaction   c_j = Σ_i μ_i p_ij                                        (eq. 26)
                  μ_{i|j} = μ_i p_ij / c_j                                   (eq. 27)
                  x⁰_j = Σ_i μ_{i|j} x_i,  P⁰_j = Σ_i μ_{i|j} [P_i + (x_i − x⁰_j)(x_i − x⁰_j)ᵀ]
    filtering     model j's filter predicts from (x⁰_j, P⁰_j) and updates with z: Λ_j = N(z; ẑ_j, S_j)
    mode update   μ_j ∝ c_j Λ_j;  log p(z_k | z_{1:k-1}) = log Σ_j c_j Λ_j
    combination   x = Σ_j μ_j x_j,  P = Σ_j μ_j [P_j + (x_j − x)(x_j − x)ᵀ]   (eq. 28 moments)

Mode probabilities live in the log domain. :meth:`InteractingMultipleModel.predict` performs
interaction and model-matched prediction and returns the *predicted* mode probabilities ``c_j``;
:meth:`update` turns them into posteriors. The model-matched filters may be any of the Kalman
family (:class:`~torchtrack.filters.kalman.filter.KalmanFilter`, ``ExtendedKalmanFilter``,
``UnscentedKalmanFilter``) and may differ in dynamics, process noise and control input
(:class:`ModeMatched` wraps one mode of a :class:`~torchtrack.models.ModeControlInput`).

Everything is differentiable in the models' noise parameters and in the transition matrix when it
is given as a :class:`~torchtrack.params.RowStochastic`; the exact marginal log-likelihood
``Σ_k log p(z_k | z_{1:k-1})`` is :attr:`IMMResult.log_likelihood`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.filters.kalman.filter import ExtendedKalmanFilter, GaussianState
from torchtrack.gaussian import moment_match
from torchtrack.models.measurement import MeasurementModel
from torchtrack.models.motion import ModeControlInput, MotionModel
from torchtrack.params import RowStochastic


class IMMState(NamedTuple):
    """Per-model Gaussians and mode probabilities: ``log_prob (*, M)``, ``mean (*, M, n)``,
    ``cov (*, M, n, n)``."""

    log_prob: Tensor
    mean: Tensor
    cov: Tensor


class IMMUpdateInfo(NamedTuple):
    """What an IMM update exposes besides the new state."""

    log_likelihood: Tensor        # (*,)  log Σ_j c_j Λ_j (0 where missing)
    model_log_likelihood: Tensor  # (*, M) log Λ_j (0 where missing)
    nis: Tensor                   # (*, M) per-model νᵀ S⁻¹ ν (0 where missing)
    present: Tensor               # (*,) bool


class IMMResult(NamedTuple):
    """A filtered sequence (``T`` steps)."""

    mean: Tensor            # (T, *, n) combined estimate
    cov: Tensor             # (T, *, n, n)
    mode_prob: Tensor       # (T, *, M)
    model_mean: Tensor      # (T, *, M, n)
    log_likelihood: Tensor  # (*,) Σ_k log p(z_k | z_{1:k-1})


def check_transition(P: Tensor, num_models: int, name: str = "mode transition matrix", atol: float = 1e-6) -> None:
    """Raise :class:`TorchtrackError` unless ``P (M, M)`` is non-negative with rows summing to one."""
    if P.dim() != 2 or P.shape != (num_models, num_models):
        raise TorchtrackError(f"{name} must have shape ({num_models}, {num_models}) for {num_models} models; "
                              f"got {tuple(P.shape)}")
    check_probabilities(P, f"rows of {name}", atol)


class TransitionMatrix(nn.Module):
    """A fixed (buffer) or learnable (:class:`RowStochastic`) mode transition matrix; call for ``(M, M)``."""

    def __init__(self, value, num_models: int, name: str = "mode transition matrix"):
        super().__init__()
        self.learned = value if isinstance(value, RowStochastic) else None
        if self.learned is None:
            self.register_buffer("fixed", torch.as_tensor(value, dtype=torch.get_default_dtype()))
        check_transition(self().detach(), num_models, name)

    def forward(self) -> Tensor:
        return self.learned() if self.learned is not None else self.fixed


def check_probabilities(p: Tensor, name: str, atol: float = 1e-5) -> None:
    """Raise unless ``p (*, K)`` is non-negative and sums to one over the last axis."""
    if p.dim() < 1 or bool((p < 0).any()) or not bool(torch.isfinite(p).all()):
        raise TorchtrackError(f"{name} must be finite and non-negative")
    sums = p.sum(-1)
    if not bool(((sums - 1).abs() <= atol).all()):
        raise TorchtrackError(f"{name} must sum to 1 over the last axis; got sums in "
                              f"[{float(sums.min()):.6g}, {float(sums.max()):.6g}]")


def probabilities_or_uniform(p, K: int, name: str, like: Tensor) -> Tensor:
    """``p (*, K)`` as a tensor with ``like``'s dtype and device (uniform over ``K`` when ``None``),
    checked to have ``K`` entries that form a distribution."""
    if p is None:
        p = torch.full((K,), 1.0 / K, dtype=like.dtype, device=like.device)
    p = torch.as_tensor(p, dtype=like.dtype, device=like.device)
    if p.shape[-1] != K:
        raise TorchtrackError(f"{name} must have {K} entries; got shape {tuple(p.shape)}")
    check_probabilities(p, name)
    return p


def mix(state: IMMState, log_transition: Tensor) -> IMMState:
    """Interaction step (eq. 26–27): mixed initial conditions and predicted mode log-probabilities.

    ``log_transition (M, M)``; returns ``IMMState(log c (*, M), x⁰ (*, M, n), P⁰ (*, M, n, n))``.
    """
    a = state.log_prob.unsqueeze(-1) + log_transition            # (*, i, j): log μ_i p_ij; softmax over i: μ_{i|j}
    mean0, cov0 = moment_match(a, state.mean.unsqueeze(-2), state.cov.unsqueeze(-3), dim=-2)
    return IMMState(torch.logsumexp(a, dim=-2), mean0, cov0)


def combine(state: IMMState) -> GaussianState:
    """Combined estimate: moment match of the model-conditioned Gaussians (``(*, n)``, ``(*, n, n)``)."""
    return GaussianState(*moment_match(state.log_prob, state.mean, state.cov))


class ModeMatched(MotionModel):
    """One mode ``j`` of a :class:`ModeControlInput`: ``f(x) = F x + G u_j``, ``Q = σ_j² G Gᵀ``.

    Affine, so it is declared nonlinear and filtered by the EKF, which is exact for affine models
    (``transition`` adds the control offset; ``jacobian`` is ``F``). Parameters are shared with the
    wrapped model, so gradients reach its ``sigma``.
    """

    is_linear = False

    def __init__(self, motion: ModeControlInput, mode: int):
        super().__init__()
        if not 0 <= mode < motion.num_modes:
            raise TorchtrackError(f"mode must be in [0, {motion.num_modes}); got {mode}")
        self.base = motion
        self.mode = mode
        self.state_dim = motion.state_dim

    def transition(self, x: Tensor, dt) -> Tensor:
        mode = torch.tensor(self.mode, device=x.device)
        return self.base.transition(x, dt, mode).to(x.dtype)

    def jacobian(self, x: Tensor, dt) -> Tensor:
        return self.base.transition_matrix(dt).to(x.dtype)

    def process_noise(self, dt) -> Tensor:
        return self.base.process_noise(dt, torch.tensor(self.mode, device=self.base.sigma.raw.device))


class MultipleModelFilter(nn.Module):
    """What the IMMs share on :class:`IMMState` (the initial state, its check, the combined estimate and
    :meth:`run`); subclasses give ``state_dim``, ``num_models``, ``predict`` and ``update``."""

    state_dim: int
    num_models: int

    def initial_state(self, mean: Tensor, cov: Tensor, mode_prob: Tensor | None = None) -> IMMState:
        """Every model starts at ``mean (*, n)``, ``cov (*, n, n)``; ``mode_prob (*, M)`` (uniform if None)."""
        M = self.num_models
        if mean.shape[-1] != self.state_dim or cov.shape[-2:] != (self.state_dim, self.state_dim):
            raise TorchtrackError(f"IMM initial state must be (*, {self.state_dim}) and (*, {self.state_dim}, "
                                  f"{self.state_dim}); got {tuple(mean.shape)} and {tuple(cov.shape)}")
        mode_prob = probabilities_or_uniform(mode_prob, M, "mode probabilities", mean)
        batch = torch.broadcast_shapes(mean.shape[:-1], cov.shape[:-2], mode_prob.shape[:-1])
        n = self.state_dim
        return IMMState(torch.log(mode_prob).expand(*batch, M), mean.unsqueeze(-2).expand(*batch, M, n),
                        cov.unsqueeze(-3).expand(*batch, M, n, n))

    def _check(self, state: IMMState) -> None:
        M, n = self.num_models, self.state_dim
        if state.log_prob.shape[-1] != M or state.mean.shape[-2:] != (M, n) or state.cov.shape[-3:] != (M, n, n):
            raise TorchtrackError(f"IMM state must be log_prob (*, {M}), mean (*, {M}, {n}), cov (*, {M}, {n}, "
                                  f"{n}); got {tuple(state.log_prob.shape)}, {tuple(state.mean.shape)}, "
                                  f"{tuple(state.cov.shape)}")

    def combine(self, state: IMMState) -> GaussianState:
        return combine(state)

    def run(self, measurements: Tensor, init: IMMState, dt=1.0, mask: Tensor | None = None,
            predict_first: bool = True) -> IMMResult:
        """Filter ``measurements (T, *, m)`` (NaN rows or ``mask (T, *)`` False = missing) from ``init``."""
        if measurements.dim() < 2:
            raise TorchtrackError(f"IMM: measurements must have shape (T, *, m); got {tuple(measurements.shape)}")
        state = init
        steps = []
        total = 0.0
        for k in range(measurements.shape[0]):
            if predict_first or k > 0:
                state = self.predict(state, dt)
            state, info = self.update(state, measurements[k], None if mask is None else mask[k])
            steps.append((*combine(state), state.log_prob.exp(), state.mean))
            total = total + info.log_likelihood
        return IMMResult(*(torch.stack(t) for t in zip(*steps)), total)


class InteractingMultipleModel(MultipleModelFilter):
    """IMM over ``filters`` (one model-matched Gaussian filter per mode) and a transition matrix.

    ``transition``: a ``(M, M)`` row-stochastic tensor (zeros allowed, fixed) or a
    :class:`RowStochastic` (learnable). All filters must share the state and measurement sizes.
    """

    def __init__(self, filters: Sequence[nn.Module], transition):
        super().__init__()
        if len(filters) == 0:
            raise TorchtrackError("IMM needs at least one model-matched filter")
        n = {f.state_dim for f in filters}
        if len(n) != 1:
            raise TorchtrackError(f"IMM models must share a state layout; got mismatched model state sizes "
                                  f"{[f.state_dim for f in filters]}")
        m = {f.measurement.meas_dim for f in filters}
        if len(m) != 1:
            raise TorchtrackError(f"IMM models must share the measurement size; got "
                                  f"{[f.measurement.meas_dim for f in filters]}")
        self.filters = nn.ModuleList(filters)
        self.transition = TransitionMatrix(transition, len(filters))
        self.state_dim = n.pop()
        self.meas_dim = m.pop()

    @classmethod
    def from_mode_control(cls, motion: ModeControlInput, measurement: MeasurementModel,
                          transition) -> InteractingMultipleModel:
        """One EKF (exact for these affine models) per mode of ``motion`` — the gate paper's model sets."""
        return cls([ExtendedKalmanFilter(ModeMatched(motion, j), measurement) for j in range(motion.num_modes)],
                   transition)

    @property
    def num_models(self) -> int:
        return len(self.filters)

    def predict(self, state: IMMState, dt=1.0) -> IMMState:
        """Interaction + model-matched prediction; returns predicted mode log-probabilities ``log c_j``."""
        self._check(state)
        mixed = mix(state, torch.log(self.transition().to(state.mean)))
        preds = [f.predict(GaussianState(mixed.mean[..., j, :], mixed.cov[..., j, :, :]), dt)
                 for j, f in enumerate(self.filters)]
        return IMMState(mixed.log_prob, torch.stack([s.mean for s in preds], -2),
                        torch.stack([s.cov for s in preds], -3))

    def update(self, state: IMMState, z: Tensor, mask: Tensor | None = None,
               check: bool = True) -> tuple[IMMState, IMMUpdateInfo]:
        """Model-matched updates with ``z (*, m)`` and the mode-probability update."""
        self._check(state)
        posts, infos = zip(*(f.update(GaussianState(state.mean[..., j, :], state.cov[..., j, :, :]), z, mask, check)
                             for j, f in enumerate(self.filters)))
        ll = torch.stack([i.log_likelihood for i in infos], -1)
        joint = state.log_prob + ll
        total = torch.logsumexp(joint, -1)
        new = IMMState(joint - total.unsqueeze(-1), torch.stack([s.mean for s in posts], -2),
                       torch.stack([s.cov for s in posts], -3))
        return new, IMMUpdateInfo(total, ll, torch.stack([i.nis for i in infos], -1), infos[-1].present)

    def predicted_measurement(self, state: IMMState) -> tuple[Tensor, Tensor, Tensor]:
        """Mixture measurement prediction of a *predicted* state (eq. 29–30).

        Returns ``log weight (*, M)`` (= ``log c_j``), ``ẑ_j (*, M, m)`` and ``S_j (*, M, m, m)``.
        """
        self._check(state)
        zs, Ss, _ = zip(*(f._moments(GaussianState(state.mean[..., j, :], state.cov[..., j, :, :]))
                          for j, f in enumerate(self.filters)))
        return state.log_prob, torch.stack(zs, -2), torch.stack(Ss, -3)

__all__ = [
    "IMMResult", "IMMState", "IMMUpdateInfo", "InteractingMultipleModel", "ModeMatched", "MultipleModelFilter",
    "TransitionMatrix",
    "check_probabilities", "check_transition", "combine", "mix",
]
