"""Multiple-model particle filter and the joint tracking & classification (JTC) bank.

Angelova, Mihaylova & Semerdjiev, "Monte Carlo algorithm for maneuvering target tracking and
classification" (``shared/seeds/jtc-particle-filter.md``), section 3. One multiple-model particle
filter per class ``c`` runs on hybrid particles ``{x, m, c}``; all classes and all runs are one
flat batch, so a step is a fixed number of tensor operations whatever ``C``, ``N`` or the number of
runs.

Per scan ``k`` and class ``c`` (the paper's algorithm, step 2):

* mode   ``m_k^j ~ p^c_{m_{k-1}^j, ·}`` (Markov chain, Walker alias method, one uniform per particle);
* state  ``x_k^j = F x_{k-1}^j + G (u^c(m_k^j) + w)``, ``w ~ N(0, σ^c(m_k^j)² I)`` — eq. (7), the
  :class:`~torchtrack.models.motion.ModeControlInput` model, written elementwise on coordinates;
* weight ``w_k^j = f(z_k | x_k^j) g_c(v̂_{k−1}^c)`` — eq. (9); ``f`` is the range–bearing
  likelihood ``N(z; h(x), R)`` of eq. (8); ``g_c`` the speed likelihood (after ``warmup`` scans);
* ``L(c) = Σ_j w_k^j`` (for the equal weights ``1/N`` left by resampling; in general the
  weighted sum), then ``P(c | Z^k) ∝ L(c) P(c | Z^{k−1})`` — step 3;
* systematic resampling of each class, ``x̂_k^c = (1/N) Σ_j x_k^j``,
  ``P^c(m_k = l) = #{j : m_k^j = l} / N``, combined ``x̂_k = Σ_c P(c | Z^k) x̂_k^c`` — eq. (6).

The speed likelihoods (piecewise linear in the estimated speed ``v``) are constant per class
within a scan, so they change the class probabilities but not the particles of a class.

Particles are stored **coordinate-major**, ``(4, *B, C, N)`` for ``[x, y, vx, vy]``, so that every
coordinate is one contiguous ``(*B, C, N)`` tensor and the models become elementwise operations.
Gradients: the per-particle noise is reparameterised; when autograd is on, resampling uses the
stop-gradient correction of Ścibior & Wood (2021) as in :mod:`torchtrack.filters.particle.filter`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.filters.particle import resampling
from torchtrack.filters.particle.filter import check_num_particles, noise_factor
from torchtrack.gaussian import LOG_2PI, log_prob_from_cholesky
from torchtrack.models.measurement import MeasurementModel, RangeBearing, wrap_angle
from torchtrack.models.motion import ModeControlInput

G = 9.81
# The paper's speed envelopes, one row per class: (v_low, v_high, g(v ≤ v_low), g(v > v_high)).
PAPER_SPEED_ENVELOPES = ((100.0, 300.0, 0.8, 0.1), (150.0, 650.0, 0.1, 0.95))


def paper_transition_matrix() -> Tensor:
    """The paper's mode transition matrix (0-based rows: from-mode).

    The paper prints ``p_ii = 0.7``, ``p_1j = 0.15`` (``j = 2…5``) and ``p_ij = 0.05`` (``j ≠ i``,
    ``i, j = 2…5``). Read literally, row 1 sums to 1.3. We read ``p_1j = 0.15`` as the return
    probability ``p_j1`` to mode 1, which makes rows 2–5 sum to exactly 1 (0.7 + 0.15 + 3·0.05), and
    spread the remaining 0.3 of row 1 equally (``p_1j = 0.075``).
    """
    P = torch.full((5, 5), 0.05, dtype=torch.float64)
    P[0, 1:] = 0.075
    P[1:, 0] = 0.15
    P.fill_diagonal_(0.7)
    return P


def speed_likelihood(v: Tensor, envelope: Tensor) -> Tensor:
    """Piecewise-linear speed likelihood of the paper's section 3.

    ``g(v) = g_lo`` for ``v ≤ v_lo``; ``g_lo + (g_hi − g_lo)(v − v_lo)/(v_hi − v_lo)`` on
    ``(v_lo, v_hi]``; ``g_hi`` for ``v > v_hi``. ``envelope (*, 4)`` rows ``(v_lo, v_hi, g_lo, g_hi)``
    broadcast against ``v (*)``. With :data:`PAPER_SPEED_ENVELOPES` this is ``g_1`` (``κ_1 = −0.7/200``)
    and ``g_2`` (``κ_2 = 0.85/500``).
    """
    lo, hi, g_lo, g_hi = envelope.unbind(-1)
    return g_lo + (g_hi - g_lo) / (hi - lo) * (torch.minimum(torch.maximum(v, lo), hi) - lo)


def paper_class_models(learnable: bool = False) -> list[ModeControlInput]:
    """The two class models: modes ``(0,0), (A,A), (A,−A), (−A,A), (−A,−A)`` with ``A = 2g`` (class 1,
    ``σ_w = 5.5`` in every mode) and ``A = 5g`` (class 2, ``σ_w = 7.5`` in mode 1, ``17.5`` otherwise)."""
    signs = torch.tensor([[0, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=torch.float64)
    return [ModeControlInput(2 * G * signs, [5.5] * 5, learnable=learnable),
            ModeControlInput(5 * G * signs, [7.5, 17.5, 17.5, 17.5, 17.5], learnable=learnable)]


class MMPFState(NamedTuple):
    particles: Tensor       # (4, *B, C, N) coordinate-major [x, y, vx, vy]
    mode: Tensor            # (*B, C, N) int64, 0-based mode index
    log_weight: Tensor      # (*B, C, N) normalised within each class
    log_class: Tensor       # (*B, C) log P(c | Z^k)
    speed: Tensor           # (*B, C) v̂_k^c, speed of each class estimate
    log_likelihood: Tensor  # (*B, C) log p̂(z_{1:k} | c) (speed likelihoods included)


class MMPFOutput(NamedTuple):
    mean: Tensor            # (*B, 4) combined estimate x̂_k, layout [x, y, vx, vy]
    class_mean: Tensor      # (*B, C, 4) x̂_k^c
    class_prob: Tensor      # (*B, C) P(c | Z^k)
    mode_prob: Tensor       # (*B, C, M) P^c(m_k = l)


class MMPFRun(NamedTuple):
    mean: Tensor            # (K, *B, 4)
    class_mean: Tensor      # (K, *B, C, 4)
    class_prob: Tensor      # (K, *B, C)
    mode_prob: Tensor       # (K, *B, C, M)
    log_likelihood: Tensor  # (*B, C)


class Noise(NamedTuple):
    """The random numbers of one step, drawn in bulk (two generator calls): ``eps (2, *B, C, N)``
    standard normal; uniforms ``u_mode (*B, C, N)`` and ``u_resample (*B, C, 1)`` (views of one draw)."""

    eps: Tensor
    u_mode: Tensor
    u_resample: Tensor


class Tables(NamedTuple):
    """Per-run constants of a step, computed once by :meth:`MultipleModelParticleFilter.tables`."""

    motion: Tensor          # (3, C·M) rows u_x, u_y, σ for every (class, mode)
    alias_prob: Tensor      # (C·M·M,) Walker alias tables of the rows of p^c, see alias_tables()
    alias: Tensor           # (C·M·M,) int64
    offset_m: Tensor        # (C, 1) c·M·M
    offset: Tensor          # (C, 1) c·M
    sensor: Tensor          # (2, 1, …, 1) radar position, broadcastable to (2, *B, C, N)
    scale: Tensor           # (2,) −1/(2σ_D²), −1/(2σ_β²)
    log_norm: Tensor        # () −log(2π σ_D σ_β)
    envelopes: Tensor | None  # (4, C) rows v_lo, v_hi, intercept, slope: g(v) = intercept + slope·clamp(v)


def alias_tables(P: Tensor) -> tuple[Tensor, Tensor]:
    """Walker's alias tables (Vose's construction) of each row of ``P (K, M)``: ``prob (K, M)`` and
    ``alias (K, M)`` such that drawing ``j`` uniformly from ``0…M−1`` and keeping it with probability
    ``prob[j]``, else taking ``alias[j]``, samples from the row. Built once per run (loops over the
    ``K·M`` table entries, not over particles)."""
    K, M = P.shape
    prob = torch.ones(K, M, dtype=torch.float64)
    alias = torch.arange(M).repeat(K, 1)
    for k in range(K):
        scaled = (P[k].double() * M).tolist()
        small = [j for j in range(M) if scaled[j] < 1.0]
        large = [j for j in range(M) if scaled[j] >= 1.0]
        while small and large:
            s, g = small.pop(), large.pop()
            prob[k, s], alias[k, s] = scaled[s], g
            scaled[g] -= 1.0 - scaled[s]
            (small if scaled[g] < 1.0 else large).append(g)
    return prob, alias


class MultipleModelParticleFilter(nn.Module):
    """A bank of multiple-model bootstrap particle filters, one per class (``C = 1``: a plain MMPF).

    Args:
        motions: one :class:`ModeControlInput` per class, all with ``M`` modes and ``ndim = 2``.
        measurement: :class:`RangeBearing` (fast elementwise path) or any measurement model of
            ``[x, y, vx, vy]``.
        transition: mode transition matrix ``(M, M)`` or ``(C, M, M)``, rows summing to 1.
        initial_mode: initial mode probabilities ``(M,)`` or ``(C, M)``.
        num_particles: ``N_c`` particles per class.
        class_prior: ``P_0(c)`` ``(C,)`` (default uniform).
        speed_envelopes: ``(C, 4)`` rows for :func:`speed_likelihood`, or ``None`` (no speed constraints).
        warmup: the speed likelihoods enter from scan ``warmup + 1`` on.
    """

    def __init__(self, motions: Sequence[ModeControlInput], measurement: MeasurementModel, transition,
                 initial_mode, num_particles: int, class_prior=None, speed_envelopes=None, warmup: int = 5):
        super().__init__()
        if len(motions) < 1 or any(not isinstance(m, ModeControlInput) or m.ndim != 2 for m in motions):
            raise TorchtrackError("motions must be a non-empty list of 2-D ModeControlInput models")
        modes = {m.num_modes for m in motions}
        if len(modes) != 1:
            raise TorchtrackError(f"all class models must have the same number of modes; got {sorted(modes)}")
        self.motions = nn.ModuleList(motions)
        self.num_classes, self.num_modes = len(motions), modes.pop()
        self.measurement = measurement
        self.num_particles = check_num_particles(num_particles)
        C, M = self.num_classes, self.num_modes
        P = torch.as_tensor(transition, dtype=torch.float64).expand(C, M, M)
        if (P < 0).any() or not torch.allclose(P.sum(-1), torch.ones(C, M, dtype=torch.float64), atol=1e-6):
            raise TorchtrackError(f"transition must be ({M}, {M}) or ({C}, {M}, {M}) with rows summing to 1")
        p0 = torch.as_tensor(initial_mode, dtype=torch.float64).expand(C, M)
        if (p0 < 0).any() or not torch.allclose(p0.sum(-1), torch.ones(C, dtype=torch.float64), atol=1e-6):
            raise TorchtrackError(f"initial_mode must be ({M},) or ({C}, {M}) probabilities summing to 1")
        pc = torch.full((C,), 1.0 / C, dtype=torch.float64) if class_prior is None else \
            torch.as_tensor(class_prior, dtype=torch.float64)
        if pc.shape != (C,) or (pc < 0).any() or abs(float(pc.sum()) - 1) > 1e-6:
            raise TorchtrackError(f"class_prior must be {C} probabilities summing to 1; got {pc.tolist()}")
        self.register_buffer("transition", P.clone())
        self.register_buffer("initial_mode", p0.clone())
        self.register_buffer("class_prior", pc)
        env = None if speed_envelopes is None else torch.as_tensor(speed_envelopes, dtype=torch.float64)
        if env is not None and (env.shape != (C, 4) or not bool((env[:, 1] > env[:, 0]).all())
                                or not bool((env[:, 2:] > 0).all())):
            raise TorchtrackError(f"speed_envelopes must be ({C}, 4) rows (v_lo < v_hi, g_lo > 0, g_hi > 0)")
        self.register_buffer("speed_envelopes", env)
        if warmup < 0:
            raise TorchtrackError(f"warmup must be >= 0; got {warmup}")
        self.warmup = int(warmup)

    # ---------------------------------------------------------------- set-up
    def tables(self, dtype: torch.dtype, batch_ndim: int = 1) -> Tables:
        """Control inputs, noise levels, alias tables of the transition rows (flattened over (class, mode)),
        the radar constants and the speed envelopes, in ``dtype``, for runs with ``batch_ndim`` dims."""
        C, M = self.num_classes, self.num_modes
        controls = torch.cat([m.controls for m in self.motions]).to(dtype).T
        sigma = torch.cat([m.sigma() for m in self.motions]).to(dtype)
        prob, alias = alias_tables(self.transition.reshape(C * M, M))
        offset = (torch.arange(C, device=prob.device) * M).unsqueeze(-1)
        env = None
        if self.speed_envelopes is not None:
            lo, hi, g_lo, g_hi = self.speed_envelopes.to(dtype).unbind(-1)
            slope = (g_hi - g_lo) / (hi - lo)
            env = torch.stack([lo, hi, g_lo - slope * lo, slope])
        meas = self.measurement
        if isinstance(meas, RangeBearing):
            sensor = meas.sensor_position.to(dtype).reshape(2, *[1] * (batch_ndim + 2))
            sig = torch.stack([meas.sigma_range(), meas.sigma_bearing()]).to(dtype)
            scale, log_norm = -0.5 / sig**2, -LOG_2PI - torch.log(sig).sum()
        else:
            sensor = scale = log_norm = torch.zeros((), dtype=dtype)
        return Tables(torch.cat([controls, sigma[None]]), prob.to(dtype).flatten(), alias.flatten(), offset * M,
                      offset, sensor, scale, log_norm, env)

    def init(self, mean: Tensor, cov: Tensor, generator: torch.Generator | None = None) -> MMPFState:
        """Step 1: ``x_0^j ~ N(mean, cov)``, ``m_0^j ~ P_0^c``; ``mean (*B, 4)``, ``cov (*B, 4, 4)``."""
        C, N = self.num_classes, self.num_particles
        L = noise_factor(cov, "initial covariance").to(mean.dtype)
        batch = torch.broadcast_shapes(mean.shape[:-1], L.shape[:-2])
        eps = torch.randn((*batch, C, N, 4, 1), generator=generator, dtype=mean.dtype, device=mean.device)
        x = mean[..., None, None, :] + (L[..., None, None, :, :] @ eps).squeeze(-1)
        p0 = self.initial_mode.to(mean.dtype).expand(*batch, C, -1).reshape(-1, self.num_modes)
        mode = resampling.multinomial(torch.log(p0), generator, N).reshape(*batch, C, N)
        zeros = torch.zeros((*batch, C), dtype=mean.dtype, device=mean.device)
        speed = torch.linalg.vector_norm(mean[..., 2:4], dim=-1)[..., None].expand(*batch, C)
        log_w = torch.full((*batch, C, N), -math.log(N), dtype=mean.dtype, device=mean.device)
        log_class = torch.log(self.class_prior).to(mean.dtype).expand(*batch, C)
        return MMPFState(x.movedim(-1, 0).contiguous(), mode, log_w, log_class.clone(), speed.clone(), zeros)

    def draw(self, batch_shape, generator: torch.Generator | None = None, dtype=torch.float32,
             device=None) -> Noise:
        """All random numbers of one step for runs of shape ``batch_shape``."""
        C, N = self.num_classes, self.num_particles
        eps = torch.randn((2, *batch_shape, C, N), generator=generator, dtype=dtype, device=device)
        rows = math.prod(batch_shape) * C
        u = torch.rand(rows * (N + 1), generator=generator, dtype=dtype, device=device)
        return Noise(eps, u[: rows * N].view(*batch_shape, C, N), u[rows * N:].view(*batch_shape, C, 1))

    # ---------------------------------------------------------------- one scan
    def log_likelihood(self, particles: Tensor, z: Tensor, tables: Tables) -> Tensor:
        """``log N(z; h(x^j), R)`` up to the constant ``tables.log_norm``; ``particles (4, *B, C, N)``,
        ``z (*B, m)`` → ``(*B, C, N)``. Range–bearing (eq. 8) is written elementwise."""
        meas = self.measurement
        if isinstance(meas, RangeBearing):
            d = particles[:2] - tables.sensor
            nu_r = z[..., 0, None, None] - torch.hypot(d[0], d[1])
            nu_b = wrap_angle(z[..., 1, None, None] - torch.atan2(d[0], d[1]))
            return nu_r.square_().mul_(tables.scale[0]).add_(nu_b.square_().mul_(tables.scale[1]))
        nu = meas.residual(z[..., None, None, :], meas.measure(particles.movedim(0, -1)))
        L = torch.linalg.cholesky(meas.noise_cov()).to(nu.dtype)
        return log_prob_from_cholesky(nu, torch.zeros_like(nu), L)

    def step(self, state: MMPFState, z: Tensor, dt: float, scan: int, noise: Noise,
             tables: Tables) -> tuple[MMPFState, MMPFOutput]:
        """One scan ``k = scan`` (1-based) of the algorithm for measurement ``z (*B, 2)``."""
        return self.kernel(state, z, dt, tables.envelopes is not None and scan > self.warmup, noise, tables)

    def kernel(self, state: MMPFState, z: Tensor, dt: float, use_speed: bool, noise: Noise,
               tables: Tables) -> tuple[MMPFState, MMPFOutput]:
        """:meth:`step` with the speed likelihoods switched by ``use_speed`` (a function of the
        shapes and flags only, so that ``torch.compile`` traces it once)."""
        N, M = self.num_particles, self.num_modes
        x = state.particles
        # prediction: mode jump by Walker's alias method (one uniform: j = ⌊M u⌋, keep j with
        # probability prob[m, j] judged by the fraction M u − j, else alias[m, j]), then eq. (7)
        # elementwise: x_k = x + dt·[v + dt/2·a; a] with a = u(m) + σ(m) ε
        t = noise.u_mode * M
        j = t.long()
        flat = torch.add(j, state.mode, alpha=M).add_(tables.offset_m)
        mode = torch.where(t - j < tables.alias_prob.take(flat), j, tables.alias.take(flat))
        idx = mode + tables.offset
        par = tables.motion.index_select(1, idx.flatten()).view(3, *idx.shape)
        acc = torch.addcmul(par[:2], par[2], noise.eps)
        x = torch.add(x, torch.cat([torch.add(x[2:], acc, alpha=0.5 * dt), acc]), alpha=dt)
        # weights w_k^j and class likelihoods L(c) = Σ_j w_k^j, eq. (9)
        # (after every step the weights are equal in value, −log N; only their gradient differs)
        grad = torch.is_grad_enabled()
        ll = self.log_likelihood(x, z, tables)
        log_w = state.log_weight + ll if grad else ll
        top = log_w.detach().amax(-1, keepdim=True).clamp_min(torch.finfo(log_w.dtype).min)
        w = torch.exp(log_w - top)
        total = w.sum(-1, keepdim=True)
        log_L = (torch.log(total) + top).squeeze(-1) + (tables.log_norm if grad else tables.log_norm - math.log(N))
        if use_speed:
            lo, hi, intercept, slope = tables.envelopes      # speed_likelihood(), unrolled
            log_L = log_L + torch.log(torch.addcmul(intercept, slope, torch.clamp(state.speed, lo, hi)))
        # class probabilities, step 3 (a class with L(c) = 0 drops to 0; if all do, the prior is kept)
        log_class = state.log_class + log_L
        norm = torch.logsumexp(log_class, -1, keepdim=True)
        log_class = torch.where(torch.isneginf(norm), state.log_class, log_class - norm)
        # systematic resampling of every (run, class) row at once; an all-zero row resamples uniformly
        anc = resampling.systematic_from_uniform(w.detach() + (total == 0), noise.u_resample)
        x = x.gather(-1, anc.expand(4, *anc.shape))
        mode = mode.gather(-1, anc)
        if grad:
            new_w = resampling.resampled_log_weight(log_w, anc)
            new_w = new_w - torch.logsumexp(new_w, -1, keepdim=True).detach()
        else:
            new_w = state.log_weight
        # estimates: x̂^c, P^c(m), v̂^c, combined x̂ (eq. 6)
        class_mean = x.mean(-1).movedim(0, -1)
        counts = torch.zeros((*mode.shape[:-1], M), dtype=x.dtype, device=x.device)
        mode_prob = counts.scatter_add_(-1, mode, torch.ones((), dtype=x.dtype).expand_as(mode)).div_(N)
        speed = torch.hypot(class_mean[..., 2], class_mean[..., 3])
        class_prob = log_class.exp()
        mean = (class_prob.unsqueeze(-1) * class_mean).sum(-2)
        new = MMPFState(x, mode, new_w, log_class, speed, state.log_likelihood + log_L)
        return new, MMPFOutput(mean, class_mean, class_prob, mode_prob)

    def run(self, z_seq: Tensor, mean: Tensor, cov: Tensor, dt: float,
            generator: torch.Generator | None = None) -> MMPFRun:
        """Filter ``z_seq (K, *B, 2)`` (scans 1…K) from the prior ``N(mean, cov)`` at time 0."""
        state = self.init(mean, cov, generator)
        batch = state.log_class.shape[:-1]
        tables = self.tables(mean.dtype, len(batch))
        outs = []
        for k, z in enumerate(z_seq, start=1):
            noise = self.draw(batch, generator, mean.dtype, mean.device)
            state, out = self.step(state, z, dt, k, noise, tables)
            outs.append(out)
        stacked = [torch.stack(t) for t in zip(*outs)]
        return MMPFRun(*stacked, state.log_likelihood)


def paper_bank(num_particles: int = 3000, speed_constraints: bool = True, warmup: int = 5,
               sensor_position=(0.0, 0.0), sigma_range: float = 100.0, sigma_bearing_deg: float = 0.15,
               class_prior=(0.5, 0.5)) -> MultipleModelParticleFilter:
    """The paper's JTC bank: two classes, five modes, ``P_0(m) = (0.6, 0.1, 0.1, 0.1, 0.1)``,
    range–bearing radar (``σ_D = 100 m``, ``σ_β = 0.15°``), equal class priors, optional speed likelihoods."""
    radar = RangeBearing(sensor_position, sigma_range, math.radians(sigma_bearing_deg), learnable=False)
    return MultipleModelParticleFilter(
        paper_class_models(), radar, paper_transition_matrix(), [0.6, 0.1, 0.1, 0.1, 0.1], num_particles,
        class_prior=class_prior, speed_envelopes=PAPER_SPEED_ENVELOPES if speed_constraints else None,
        warmup=warmup)
