"""Structured fast path of the IMM for the 2-D constant-velocity layout ``[x, y, vx, vy]``.

The models are the modes of a :class:`~torchtrack.models.ModeControlInput` (``F`` of nearly constant
velocity, control ``G u_j``, ``Q_j = σ_j² G Gᵀ``, ``G = [[dt²/2 I], [dt I]]``) and the measurement is the
position (:class:`~torchtrack.models.LinearPosition`, ``H = [I 0]``). Writing the covariance in 2×2
blocks ``P = [[A, B], [Bᵀ, C]]`` (``A`` position, ``B`` position–velocity, ``C`` velocity) every
step is closed-form on 2×2 blocks, so the filter stores the 10 unique entries
``[Axx, Axy, Ayy, Bxx, Bxy, Byx, Byy, Cxx, Cxy, Cyy]`` as separate ``(*, M)`` planes and every
operation is elementwise over (tracks × models) — no batched small matmuls::

    predict   p ← p + dt v + dt²/2 u_j,   v ← v + dt u_j
              A ← A + dt (B + Bᵀ) + dt² C + σ_j² dt⁴/4 I,   B ← B + dt C + σ_j² dt³/2 I,   C ← C + σ_j² dt² I
    update    S = A + R = L Lᵀ,  W = [A; Bᵀ] L⁻ᵀ,  x ← x + W L⁻¹ ν,  P ← P − W Wᵀ
              (the shared update of torchtrack.gaussian, on the packed entries: A ← A − A S⁻¹ A,
               B ← B − A S⁻¹ B, C ← C − Bᵀ S⁻¹ B)

The axes are *not* treated as independent: although each model's filter would keep ``x`` and ``y``
apart, the IMM mixing spread ``(x_i − x⁰_j)(x_i − x⁰_j)ᵀ`` couples them, so the cross-axis entries
are carried exactly. The result equals the general :class:`InteractingMultipleModel` (tested to
round-off in float64). The packed step can be compiled with ``torch.compile`` (inductor), which fuses
the elementwise work into a few loops; on failure it falls back to eager execution.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.filters.imm.filter import (
    IMMState,
    IMMUpdateInfo,
    MultipleModelFilter,
    TransitionMatrix,
)
from torchtrack.filters.kalman.filter import presence
from torchtrack.filters.kalman.lanes import Compiled
from torchtrack.gaussian import cholesky_entries, gaussian_log_likelihood, solve_lower_entries
from torchtrack.models.measurement import LinearPosition
from torchtrack.models.motion import ModeControlInput

# (row, col) of the 10 packed covariance entries in the 4×4 matrix over [x, y, vx, vy]
_IDX = [(0, 0), (0, 1), (1, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3)]
_ROW, _COL = map(list, zip(*_IDX))


def pack(state: IMMState) -> tuple[Tensor, Tensor, Tensor]:
    """``IMMState`` → batch-last planes ``log_prob (M, B)``, ``mean (4, M, B)``, ``cov (10, M, B)``.

    ``B`` is the flattened batch; the innermost (contiguous) axis is the batch, so compiled loops
    vectorise over tracks.
    """
    M = state.log_prob.shape[-1]
    log_prob = state.log_prob.reshape(-1, M).transpose(0, 1).contiguous()
    mean = state.mean.reshape(-1, M, 4).permute(2, 1, 0).contiguous()
    cov = state.cov[..., _ROW, _COL].reshape(-1, M, 10).permute(2, 1, 0).contiguous()
    return log_prob, mean, cov


def unpack(log_prob: Tensor, mean: Tensor, cov: Tensor, batch: torch.Size) -> IMMState:
    """Inverse of :func:`pack` for batch shape ``batch``: ``(*, M)``, ``(*, M, 4)``, symmetric ``(*, M, 4, 4)``."""
    M = log_prob.shape[0]
    c = cov.permute(2, 1, 0)                                 # (B, M, 10)
    P = cov.new_zeros(c.shape[0], M, 4, 4)
    P[..., _ROW, _COL] = c
    P[..., _COL, _ROW] = c
    return IMMState(log_prob.transpose(0, 1).reshape(*batch, M), mean.permute(2, 1, 0).reshape(*batch, M, 4),
                    P.reshape(*batch, M, 4, 4))


def mix_packed(log_prob: Tensor, mean: Tensor, cov: Tensor, transition: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Interaction (eq. 26–27) on packed planes; ``transition (M, M)`` holds ``p_ij``; returns ``(log c, x⁰, P⁰)``.

    Mode probabilities are exponentiated once (they are normalised, so the largest is ≥ 1/M and the
    mixing weights cannot all underflow); ``c_j`` is floored at the smallest normal number so that an
    unreachable mode gets weight 0 instead of NaN. The spread is taken about model 0's mean,
    ``Σ_i μ_{i|j} (x_i − x⁰_j)(·)ᵀ = Σ_i μ_{i|j} e_i e_iᵀ − f_j f_jᵀ`` with ``e_i = x_i − x_0``,
    ``f_j = x⁰_j − x_0``: the differences are of the size of the model spread, so nothing cancels.
    """
    mu = log_prob.exp()                                      # (i, B)
    a = mu.unsqueeze(1) * transition.unsqueeze(-1)           # (i, j, B): μ_i p_ij
    c = a.sum(0).clamp_min(torch.finfo(a.dtype).tiny)        # (j, B)
    w = a / c                                                # μ_{i|j}
    e = mean - mean[:, :1]                                   # (4, i, B)
    f = (e.unsqueeze(2) * w).sum(1)                          # (4, j, B)
    second = cov + e[_ROW] * e[_COL]                         # (10, i, B)
    cov0 = (second.unsqueeze(2) * w).sum(1) - f[_ROW] * f[_COL]
    return c.log(), mean[:, :1] + f, cov0


def predict_packed(mean: Tensor, cov: Tensor, dt: float, q: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Model-matched prediction; ``q (M,)`` = σ_j², ``u (2, M)`` control accelerations."""
    Axx, Axy, Ayy, Bxx, Bxy, Byx, Byy, Cxx, Cxy, Cyy = cov.unbind(0)
    h = 0.5 * dt * dt
    u, q = u.unsqueeze(-1), q.unsqueeze(-1)
    q11, q12, q22 = q * (h * h), q * (h * dt), q * (dt * dt)
    mean = torch.cat([mean[:2] + dt * mean[2:] + h * u, mean[2:] + dt * u])
    dt2 = dt * dt
    cov = torch.stack([
        Axx + 2 * dt * Bxx + dt2 * Cxx + q11,
        Axy + dt * (Bxy + Byx) + dt2 * Cxy,
        Ayy + 2 * dt * Byy + dt2 * Cyy + q11,
        Bxx + dt * Cxx + q12,
        Bxy + dt * Cxy,
        Byx + dt * Cxy,
        Byy + dt * Cyy + q12,
        Cxx + q22,
        Cxy,
        Cyy + q22,
    ])
    return mean, cov


def update_packed(log_prob: Tensor, mean: Tensor, cov: Tensor, z: Tensor, R: Tensor, present: Tensor | None = None
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Model-matched updates and mode update; ``z (2, B)``, ``R (3,)`` = ``[Rxx, Rxy, Ryy]``, ``present (B,)``.

    The shared update of :mod:`torchtrack.gaussian` on packed entries: ``S = A + R = L Lᵀ``
    (:func:`~torchtrack.gaussian.cholesky_entries`), the whitened innovation ``L⁻¹ ν`` and the rows of
    ``W = P Hᵀ L⁻ᵀ`` (``P Hᵀ`` is the first two columns of ``P``: ``[A; Bᵀ]``), then ``x⁺ = x + W L⁻¹ ν``
    and ``P⁺ = P − W Wᵀ``. Returns ``(log_prob, mean, cov, total log-likelihood (B,), model
    log-likelihoods (M, B), NIS (M, B), ok (M, B))`` (``ok``: ``S`` was positive definite).
    """
    px, py, vx, vy = mean.unbind(0)
    Axx, Axy, Ayy, Bxx, Bxy, Byx, Byy, Cxx, Cxy, Cyy = cov.unbind(0)
    Sxy = Axy + R[1]
    L, ok = cholesky_entries([[Axx + R[0], Sxy], [Sxy, Ayy + R[2]]])
    white = solve_lower_entries(L, [z[0] - px, z[1] - py])
    nis = white[0] * white[0] + white[1] * white[1]
    ll = gaussian_log_likelihood(nis, 2.0 * (torch.log(L[0][0]) + torch.log(L[1][1])), 2)
    W = [solve_lower_entries(L, row) for row in ([Axx, Axy], [Axy, Ayy], [Bxx, Byx], [Bxy, Byy])]
    new_mean = torch.stack([c + w[0] * white[0] + w[1] * white[1] for c, w in zip((px, py, vx, vy), W)])
    new_cov = torch.stack([c - (W[i][0] * W[j][0] + W[i][1] * W[j][1]) for c, (i, j) in zip(cov.unbind(0), _IDX)])
    if present is not None:
        ll = torch.where(present, ll, torch.zeros_like(ll))
        nis = torch.where(present, nis, torch.zeros_like(nis))
        new_mean = torch.where(present, new_mean, mean)
        new_cov = torch.where(present, new_cov, cov)
    joint = log_prob + ll
    total = torch.logsumexp(joint, 0)
    return joint - total, new_mean, new_cov, total, ll, nis, ok


def combine_packed(log_prob: Tensor, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """Combined estimate on packed planes: ``(4, B)`` mean and ``(10, B)`` covariance entries."""
    w = log_prob.exp()
    m = (mean * w).sum(1)
    d = mean - m.unsqueeze(1)
    return m, ((cov + d[_ROW] * d[_COL]) * w).sum(1)


def step_packed(log_prob: Tensor, mean: Tensor, cov: Tensor, z: Tensor, transition: Tensor, q: Tensor, u: Tensor,
                R: Tensor, dt: float):
    """One full IMM cycle (interaction, prediction, update, combination) on packed planes; ``z (2, B)``.

    Returns ``(log_prob, mean, cov, total log-likelihood (B,), combined mean (4, B), combined cov (10, B))``.
    """
    log_c, mean0, cov0 = mix_packed(log_prob, mean, cov, transition)
    mean1, cov1 = predict_packed(mean0, cov0, dt, q, u)
    log_prob, mean2, cov2, total, *_ = update_packed(log_c, mean1, cov1, z, R)
    cm, cc = combine_packed(log_prob, mean2, cov2)
    return log_prob, mean2, cov2, total, cm, cc


compiled_step = Compiled(step_packed, "the IMM step", dynamic=False)


class ConstantVelocityIMM(MultipleModelFilter):
    """Fast IMM for ``[x, y, vx, vy]`` with the modes of a :class:`ModeControlInput` and position measurements.

    Same interface as :class:`InteractingMultipleModel` (``initial_state``, ``predict``, ``update``,
    ``predicted_measurement``, ``combine``, ``run``) on :class:`IMMState`; :meth:`run_packed` keeps the
    packed planes over a whole sequence (the fast loop). Differentiable in ``motion.sigma``,
    ``measurement.sigma`` and a :class:`RowStochastic` transition matrix.
    """

    def __init__(self, motion: ModeControlInput, measurement: LinearPosition, transition):
        super().__init__()
        if motion.ndim != 2 or measurement.meas_dim != 2 or measurement.state_dim != 4:
            raise TorchtrackError("ConstantVelocityIMM needs a 2-D ModeControlInput and a 2-D LinearPosition "
                                  f"on a 4-state layout; got ndim={motion.ndim}, meas_dim={measurement.meas_dim}, "
                                  f"state_dim={measurement.state_dim}")
        self.motion = motion
        self.measurement = measurement
        self.transition = TransitionMatrix(transition, motion.num_modes)
        self.state_dim = 4
        self.meas_dim = 2

    @property
    def num_models(self) -> int:
        return self.motion.num_modes

    def _params(self, like: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        q = (self.motion.sigma() ** 2).to(like)
        u = self.motion.controls.to(like).transpose(0, 1)
        R = self.measurement.noise_cov().to(like)
        return self.transition().to(like), q, u, torch.stack([R[0, 0], R[0, 1], R[1, 1]])

    def predict(self, state: IMMState, dt: float = 1.0) -> IMMState:
        P, q, u, _ = self._params(state.mean)
        log_c, m, c = mix_packed(*pack(state), P)
        m, c = predict_packed(m, c, float(dt), q, u)
        return unpack(log_c, m, c, state.log_prob.shape[:-1])

    def update(self, state: IMMState, z: Tensor, mask: Tensor | None = None,
               check: bool = True) -> tuple[IMMState, IMMUpdateInfo]:
        if z.shape[-1] != 2:
            raise TorchtrackError(f"ConstantVelocityIMM: z must have shape (*, 2); got {tuple(z.shape)}")
        batch = state.log_prob.shape[:-1]
        present, z = presence(z, mask)
        present, z = present.expand(batch), z.expand(*batch, 2)
        R = self._params(state.mean)[3]
        log_prob, m2, c2, total, ll, nis, ok = update_packed(*pack(state), z.reshape(-1, 2).transpose(0, 1), R,
                                                             present.reshape(-1))
        if check and not bool(ok.all()):
            raise TorchtrackError("ConstantVelocityIMM: innovation covariance S is not positive definite")
        M = self.num_models
        info = IMMUpdateInfo(total.reshape(batch), ll.transpose(0, 1).reshape(*batch, M),
                             nis.transpose(0, 1).reshape(*batch, M), present)
        return unpack(log_prob, m2, c2, batch), info

    def predicted_measurement(self, state: IMMState) -> tuple[Tensor, Tensor, Tensor]:
        """``log c (*, M)``, ``ẑ_j (*, M, 2)``, ``S_j (*, M, 2, 2)`` of a predicted state (eq. 30)."""
        R = self.measurement.noise_cov().to(state.cov)
        return state.log_prob, state.mean[..., :2], state.cov[..., :2, :2] + R

    def run_packed(self, measurements: Tensor, init: IMMState, dt: float = 1.0, compile: bool = False):
        """Fast loop over ``measurements (T, *, 2)`` (all present) in the packed batch-last layout.

        Returns the final packed state ``(log_prob (M, B), mean (4, M, B), cov (10, M, B))``, the
        combined means ``(T, *, 4)`` and the total log-likelihood ``(*,)``.
        """
        P, q, u, R = self._params(init.mean)
        step = compiled_step if compile else step_packed
        batch = init.log_prob.shape[:-1]
        log_prob, m, c = pack(init)
        z = measurements.expand(-1, *batch, 2).reshape(measurements.shape[0], -1, 2).permute(0, 2, 1).contiguous()
        means = []
        total = 0.0
        for k in range(z.shape[0]):
            log_prob, m, c, ll, cm, _ = step(log_prob, m, c, z[k], P, q, u, R, float(dt))
            means.append(cm)
            total = total + ll
        means = torch.stack(means).permute(0, 2, 1).reshape(z.shape[0], *batch, 4)
        return (log_prob, m, c), means, total.reshape(batch)


__all__ = [
    "ConstantVelocityIMM", "combine_packed", "compiled_step", "mix_packed", "pack", "predict_packed",
    "step_packed", "unpack", "update_packed",
]
