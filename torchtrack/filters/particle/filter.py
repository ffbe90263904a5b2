"""Bootstrap particle filter, batched over runs × particles and differentiable.

State: :class:`ParticleState` with particles ``(*B, N, n)``, **normalised** log-weights ``(*B, N)``
(``logsumexp = 0``) and the running log-likelihood estimate ``(*B,)``. With unnormalised weights
``U_k = U_{k-1} + log g(z_k | x_k)`` the estimate is ``log p̂(z_{1:k}) = logsumexp(U_k) − log N``
(unbiased for ``p(z_{1:k})`` on the natural scale); the filter carries ``W = U − logsumexp(U)`` and
adds each ``logsumexp`` into ``log_likelihood`` so that weights never drift in magnitude — the same
function of the parameters, gradients included.

One step (Gordon et al. 1993; Doucet, de Freitas & Gordon 2001, ch. 1):

1. predict (bootstrap proposal)  ``x_k^i = f(x_{k-1}^i) + L_Q ε^i``, ``ε^i ~ N(0, I)``, ``L_Q L_Qᵀ = Q``
   (reparameterised, so gradients reach the process noise through the particles);
2. weight  ``W^i ← W^i + log N(z_k; h(x_k^i), R)``; ``log p̂ += logsumexp W``; renormalise;
3. resample where ``ESS = 1 / Σ_i (w^i)² < threshold · N`` (or at every step), with ancestor
   weights from :func:`~torchtrack.filters.particle.resampling.resampled_log_weight` (stop-gradient
   correction of Ścibior & Wood 2021 by default, soft resampling as an option);
4. optionally regularise (Musso, Oudjane & Le Gland 2001): ``x^i += h L_Σ ε^i`` with ``Σ`` the
   weighted particle covariance before resampling and ``h`` the ``jitter`` bandwidth.

Model parameters may carry the batch shape ``*B`` of the runs (e.g. one noise level per run), so
that per-run gradients come from one backward pass.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.filters.particle import resampling
from torchtrack.gaussian import log_prob_from_cholesky, symmetrize
from torchtrack.models.measurement import MeasurementModel
from torchtrack.models.motion import MotionModel


class ParticleState(NamedTuple):
    """A weighted particle system; see the module docstring for the weight convention."""

    particles: Tensor       # (*B, N, n)
    log_weight: Tensor      # (*B, N) normalised log-weights
    log_likelihood: Tensor  # (*B,) log p̂(z_{1:k})


class ParticleUpdateInfo(NamedTuple):
    log_likelihood: Tensor  # (*B,) log p̂(z_k | z_{1:k-1})
    ess: Tensor             # (*B,) effective sample size before resampling
    resampled: Tensor       # (*B,) bool


class ParticleRunResult(NamedTuple):
    mean: Tensor            # (T, *B, n) posterior means
    cov: Tensor             # (T, *B, n, n) posterior covariances
    ess: Tensor             # (T, *B)
    log_likelihood: Tensor  # (*B,) log p̂(z_{1:T})


def check_num_particles(num_particles: int) -> int:
    """``num_particles`` as an ``int`` ≥ 1, else :class:`TorchtrackError`."""
    if isinstance(num_particles, bool) or int(num_particles) != num_particles or num_particles < 1:
        raise TorchtrackError(f"num_particles must be a positive integer; got {num_particles!r}")
    return int(num_particles)


def normalize(log_weight: Tensor, log_likelihood: Tensor) -> tuple[Tensor, Tensor]:
    """Fold ``logsumexp(log_weight)`` into ``log_likelihood`` and renormalise.

    A row whose weights are all ``-inf`` (degenerate: no particle explains the data) is reset to
    uniform weights and its ``log_likelihood`` becomes ``-inf``: estimates stay finite, never NaN.
    """
    w, lse = resampling.normalized_log_weights(log_weight)
    return w, log_likelihood + lse.squeeze(-1)


def effective_sample_size(log_weight: Tensor) -> Tensor:
    """``1 / Σ_i w_i²`` for normalised weights ``w = softmax(log_weight)``; ``(*B, N)`` → ``(*B,)``."""
    w = resampling.normalized_weights(log_weight)
    return 1.0 / (w * w).sum(-1)


def weighted_moments(particles: Tensor, log_weight: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted mean ``(*B, n)`` and covariance ``(*B, n, n)`` of particles ``(*B, N, n)``."""
    w = resampling.normalized_weights(log_weight).unsqueeze(-1)
    mean = (w * particles).sum(-2)
    d = particles - mean.unsqueeze(-2)
    cov = (w * d).transpose(-1, -2) @ d
    return mean, symmetrize(cov)


def noise_factor(Q: Tensor, what: str) -> Tensor:
    """A lower factor of a possibly rank-deficient covariance (``Q + ε·max diag·I``, ``ε`` ≈ 10 ulp)."""
    eps = 10 * torch.finfo(Q.dtype).eps * torch.diagonal(Q, dim1=-2, dim2=-1).amax(-1)
    eye = torch.eye(Q.shape[-1], dtype=Q.dtype, device=Q.device)
    L, info = torch.linalg.cholesky_ex(Q + eps[..., None, None] * eye)
    if bool((info != 0).any()):
        raise TorchtrackError(f"{what} is not positive semi-definite")
    return L


def correlated_noise(L: Tensor, shape: tuple[int, ...], generator: torch.Generator | None, like: Tensor) -> Tensor:
    """``L ε`` for ``ε ~ N(0, I)`` of ``shape (*B, N, n)``, ``L (*B, n, n)`` shared by the ``N`` rows."""
    eps = torch.randn((*shape, 1), generator=generator, dtype=like.dtype, device=like.device)
    return (L.unsqueeze(-3) @ eps).squeeze(-1)


class ParticleFilter(nn.Module):
    """Bootstrap particle filter for any motion and measurement model.

    Args:
        motion: a :class:`~torchtrack.models.motion.MotionModel` (``transition``, ``process_noise``).
        measurement: a :class:`~torchtrack.models.measurement.MeasurementModel` (``measure``,
            ``residual``, ``noise_cov``).
        num_particles: ``N`` ≥ 1.
        resampler: ``"systematic"`` (default), ``"stratified"``, ``"multinomial"`` or ``"residual"``.
        ess_threshold: resample a run when ``ESS < ess_threshold · N``; ``None`` resamples every step.
        soft_alpha: if given, soft resampling with mixture ``α w + (1 − α)/N`` instead of the
            stop-gradient correction.
        jitter: regularisation bandwidth ``h`` (``None``: no jitter).
    """

    def __init__(self, motion: MotionModel, measurement: MeasurementModel, num_particles: int,
                 resampler: str = "systematic", ess_threshold: float | None = 0.5,
                 soft_alpha: float | None = None, jitter: float | None = None):
        super().__init__()
        self.motion = motion
        self.measurement = measurement
        self.num_particles = check_num_particles(num_particles)
        self.resample_fn = resampling.get_resampler(resampler)
        if ess_threshold is not None and not 0.0 < ess_threshold <= 1.0:
            raise TorchtrackError(f"ess_threshold must lie in (0, 1] or be None; got {ess_threshold}")
        self.ess_threshold = ess_threshold
        if soft_alpha is not None:
            resampling.soft_proposal(torch.zeros(1), soft_alpha)  # validates alpha
        self.soft_alpha = soft_alpha
        if jitter is not None and jitter < 0:
            raise TorchtrackError(f"jitter must be >= 0; got {jitter}")
        self.jitter = jitter

    def init(self, mean: Tensor, cov: Tensor, generator: torch.Generator | None = None) -> ParticleState:
        """Particles drawn from ``N(mean, cov)``; ``mean (*B, n)``, ``cov (*B, n, n)``."""
        L = noise_factor(cov, "initial covariance")
        batch = torch.broadcast_shapes(mean.shape[:-1], L.shape[:-2])
        x = mean.unsqueeze(-2) + correlated_noise(L, (*batch, self.num_particles, mean.shape[-1]), generator, mean)
        log_w = torch.full(x.shape[:-1], -math.log(self.num_particles), dtype=x.dtype, device=x.device)
        return ParticleState(x, log_w, torch.zeros(batch, dtype=x.dtype, device=x.device))

    def predict(self, state: ParticleState, dt, generator: torch.Generator | None = None) -> ParticleState:
        """Bootstrap proposal: propagate every particle through the motion model with process noise."""
        x = state.particles
        L = noise_factor(self.motion.process_noise(dt), "process noise Q").to(x.dtype)
        x = self.motion.transition(x, dt) + correlated_noise(L, x.shape, generator, x)
        return state._replace(particles=x)

    def log_likelihood(self, particles: Tensor, z: Tensor) -> Tensor:
        """``log N(z; h(x^i), R)`` per particle; ``particles (*B, N, n)``, ``z (*B, m)`` → ``(*B, N)``."""
        nu = self.measurement.residual(z.unsqueeze(-2), self.measurement.measure(particles))
        L = torch.linalg.cholesky(self.measurement.noise_cov()).to(nu.dtype)
        return log_prob_from_cholesky(nu, torch.zeros_like(nu), L.unsqueeze(-3))

    def resample(self, state: ParticleState, generator: torch.Generator | None = None,
                 where: Tensor | None = None) -> ParticleState:
        """Resample the runs selected by ``where (*B,)`` (all if ``None``); see the module docstring."""
        x, log_w = state.particles, state.log_weight
        log_q = None if self.soft_alpha is None else resampling.soft_proposal(log_w, self.soft_alpha)
        ancestors = self.resample_fn(log_w.detach() if log_q is None else log_q, generator)
        new_w = resampling.resampled_log_weight(log_w, ancestors, log_q)
        new_x = x.gather(-2, ancestors.unsqueeze(-1).expand(*ancestors.shape, x.shape[-1]))
        if self.jitter:
            _, cov = weighted_moments(x.detach(), log_w.detach())
            L = noise_factor(cov, "particle covariance for jitter")
            new_x = new_x + self.jitter * correlated_noise(L, new_x.shape, generator, x)
        new_w, ll = normalize(new_w, state.log_likelihood)
        if where is None:
            return ParticleState(new_x, new_w, ll)
        return ParticleState(torch.where(where[..., None, None], new_x, x),
                             torch.where(where[..., None], new_w, log_w),
                             torch.where(where, ll, state.log_likelihood))

    def weight(self, state: ParticleState, z: Tensor) -> ParticleState:
        """Multiply the weights by ``g(z | x^i)``, ``z (*B, m)``; accumulate the likelihood estimate."""
        log_w, ll = normalize(state.log_weight + self.log_likelihood(state.particles, z), state.log_likelihood)
        return ParticleState(state.particles, log_w, ll)

    def maybe_resample(self, state: ParticleState, generator: torch.Generator | None = None
                       ) -> tuple[ParticleState, Tensor, Tensor]:
        """Resample the runs whose ESS is below threshold; returns ``(state, ess, resampled)``."""
        ess = effective_sample_size(state.log_weight)
        if self.ess_threshold is None:
            return self.resample(state, generator), ess, torch.ones_like(ess, dtype=torch.bool)
        need = ess < self.ess_threshold * self.num_particles
        return self.resample(state, generator, need), ess, need

    def update(self, state: ParticleState, z: Tensor, generator: torch.Generator | None = None
               ) -> tuple[ParticleState, ParticleUpdateInfo]:
        """:meth:`weight` by the measurement ``z (*B, m)``, then :meth:`maybe_resample`."""
        weighted = self.weight(state, z)
        new, ess, need = self.maybe_resample(weighted, generator)
        return new, ParticleUpdateInfo(weighted.log_likelihood - state.log_likelihood, ess, need)

    def run(self, z_seq: Tensor, mean: Tensor, cov: Tensor, dt, generator: torch.Generator | None = None
            ) -> ParticleRunResult:
        """Filter ``z_seq (T, *B, m)`` from the prior ``N(mean, cov)`` at time 0 (predict, then update,
        for each of the ``T`` measurements at times ``dt, 2dt, …``). Moments are taken from the
        weighted particles before resampling."""
        state = self.init(mean, cov, generator)
        steps = []
        for z in z_seq:
            state = self.weight(self.predict(state, dt, generator), z)
            moments = weighted_moments(state.particles, state.log_weight)
            state, ess, _ = self.maybe_resample(state, generator)
            steps.append((*moments, ess))
        return ParticleRunResult(*(torch.stack(t) for t in zip(*steps)), state.log_likelihood)
