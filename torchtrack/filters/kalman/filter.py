"""Kalman, extended and unscented Kalman filters, batched over any batch shape.

Filters are stateless modules (``nn.Module``) holding a motion and a measurement model (whose noise levels are
learnable); the state is passed explicitly as a :class:`GaussianState`.

Equations (the maneuver paper, eq. 3–7; Bar-Shalom et al. 2001, §5.2)::

    predict:  x⁻ = F x,   P⁻ = F P Fᵀ + Q                                   (3), (4)
    update:   S = H P⁻ Hᵀ + R,  K = P⁻ Hᵀ S⁻¹,  x⁺ = x⁻ + K (z − H x⁻)       (5), (6)
              P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   (Joseph form of (7))

Missing measurements: ``mask`` (``True`` = present) or NaN entries in ``z``; where missing, the state
passes through unchanged and the step contributes 0 to the log-likelihood and 0 to the NIS.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.filters.kalman import axes as kalman_axes
from torchtrack.filters.kalman import lanes
from torchtrack.gaussian import (
    GaussianState,
    KalmanGain,
    chi2_quantile,
    cholesky,
    innovation_cov,
    innovation_likelihood,
    joseph_cov,
    kalman_gain,
    mahalanobis_sq,
    matmul,
    posterior_cov,
    symmetrize,
)
from torchtrack.models.measurement import LinearPosition, MeasurementModel
from torchtrack.models.motion import ConstantVelocity, MotionModel


class UpdateInfo(NamedTuple):
    """What a measurement update exposes besides the new state (``present`` marks real measurements)."""

    innovation: Tensor       # (*, m)
    innovation_cov: Tensor   # (*, m, m)
    nis: Tensor              # (*,)  νᵀ S⁻¹ ν (0 where missing)
    log_likelihood: Tensor   # (*,)  log N(ν; 0, S) (0 where missing)
    present: Tensor          # (*,)  bool


class FilterResult(NamedTuple):
    """A filtered sequence: stacked posteriors over time ``T``."""

    mean: Tensor             # (T, *, n)
    cov: Tensor              # (T, *, n, n)
    nis: Tensor              # (T, *)
    log_likelihood: Tensor   # (*,) total over time


def _check_state(state: GaussianState, n: int, who: str) -> None:
    if state.mean.shape[-1] != n:
        raise TorchtrackError(f"{who}: state mean must have shape (*, {n}); got {tuple(state.mean.shape)}")
    if state.cov.shape[-2:] != (n, n):
        raise TorchtrackError(f"{who}: state cov must have shape (*, {n}, {n}); got {tuple(state.cov.shape)}")


def presence(z: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """Presence mask ``(*,)`` and ``z`` with missing rows zero-filled (so NaN never propagates)."""
    present = ~torch.isnan(z).any(-1)
    if mask is not None:
        present = present & mask.to(torch.bool)
    return present, torch.where(present.unsqueeze(-1), z, torch.zeros_like(z))


class _GaussianFilter(nn.Module):
    """Shared machinery: argument checks, masking, the Joseph-form update, ``run``."""

    name = "Kalman filter"

    def __init__(self, motion: MotionModel, measurement: MeasurementModel):
        super().__init__()
        if motion.state_dim != measurement.state_dim:
            raise TorchtrackError(f"motion model state size {motion.state_dim} != measurement model state "
                                  f"size {measurement.state_dim}")
        self.motion = motion
        self.measurement = measurement

    @property
    def state_dim(self) -> int:
        return self.motion.state_dim

    def predict(self, state: GaussianState, dt=1.0) -> GaussianState:
        """Time update ``p(x_k | z_{1:k-1})`` from ``p(x_{k-1} | z_{1:k-1})``."""
        raise NotImplementedError

    def _moments(self, state: GaussianState) -> tuple[Tensor, Tensor, Tensor]:
        """Predicted measurement ``ẑ (*, m)``, ``S (*, m, m)`` and cross-covariance ``C = cov(x, z) (*, n, m)``."""
        raise NotImplementedError

    def update(self, state: GaussianState, z: Tensor, mask: Tensor | None = None,
               check: bool = True) -> tuple[GaussianState, UpdateInfo]:
        """Measurement update with ``z (*, m)``; ``mask (*,)`` bool, ``True`` where a measurement exists.

        The shared update of :mod:`torchtrack.gaussian` (:func:`~torchtrack.gaussian.kalman_gain`,
        :func:`~torchtrack.gaussian.innovation_likelihood`) on this filter's moments: gain from the
        cross-covariance ``C`` and ``S``; covariance ``P⁺ = P⁻ − W Wᵀ`` (``= P⁻ − K S Kᵀ``, equal to
        the Joseph form for the optimal gain; for the linear filter the Joseph form itself is used).
        """
        present, z = self._presence(state, z, mask)
        z_hat, S, C = self._moments(state)
        gain = kalman_gain(S, C, f"{self.name}: innovation covariance S", check=check)
        nu = self.measurement.residual(z, z_hat)
        mean = state.mean + (gain.gain @ nu.unsqueeze(-1)).squeeze(-1)
        nis, loglik = innovation_likelihood(gain.chol, nu)
        keep = present.unsqueeze(-1)
        post = GaussianState(torch.where(keep, mean, state.mean),
                             torch.where(keep.unsqueeze(-1), self._posterior_cov(state, gain), state.cov))
        return post, UpdateInfo(nu, S, torch.where(present, nis, 0.0), torch.where(present, loglik, 0.0), present)

    def _presence(self, state: GaussianState, z: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
        """The argument checks of :meth:`update`, then :func:`presence`."""
        m = self.measurement.meas_dim
        if z.shape[-1] != m:
            raise TorchtrackError(f"{self.name}: measurement z must have shape (*, {m}); got {tuple(z.shape)}")
        _check_state(state, self.state_dim, self.name)
        return presence(z, mask)

    def _posterior_cov(self, state: GaussianState, gain: KalmanGain) -> Tensor:
        return posterior_cov(state.cov, gain)

    def forward(self, measurements: Tensor, init: GaussianState, dt=1.0, mask: Tensor | None = None,
                predict_first: bool = True) -> FilterResult:
        """Calling the module runs :meth:`run` (so ``torch.func.functional_call`` works on filters)."""
        return self.run(measurements, init, dt, mask, predict_first)

    def run(self, measurements: Tensor, init: GaussianState, dt=1.0, mask: Tensor | None = None,
            predict_first: bool = True, history: bool = True) -> FilterResult:
        """Filter a whole sequence ``measurements (T, *, m)`` (NaN rows or ``mask (T, *)`` = missing).

        With ``predict_first`` the prior ``init`` is for time 0 and each step predicts then updates;
        otherwise the first step only updates. Returns stacked posteriors (only the last, ``T = 1``,
        without ``history``) and the total log-likelihood ``Σ_k log p(z_k | z_{1:k-1})`` —
        differentiable in every model parameter.
        """
        if measurements.dim() < 2:
            raise TorchtrackError(f"{self.name}: measurements must have shape (T, *, m); got "
                                  f"{tuple(measurements.shape)}")
        state = init
        steps = []
        total = 0.0
        T = measurements.shape[0]
        for k in range(T):
            if predict_first or k > 0:
                state = self.predict(state, dt)
            state, info = self.update(state, measurements[k], None if mask is None else mask[k])
            if history or k == T - 1:
                steps.append((state.mean, state.cov, info.nis))
            total = total + info.log_likelihood
        return FilterResult(*(torch.stack(t) for t in zip(*steps)), total)


class KalmanFilter(_GaussianFilter):
    """Linear Kalman filter (eq. 3–7); models must be linear."""

    name = "Kalman filter"

    def __init__(self, motion: MotionModel, measurement: MeasurementModel):
        super().__init__(motion, measurement)
        if not (motion.is_linear and measurement.is_linear):
            raise TorchtrackError("KalmanFilter needs linear models; use ExtendedKalmanFilter or "
                                  "UnscentedKalmanFilter")

    def predict(self, state: GaussianState, dt=1.0) -> GaussianState:
        _check_state(state, self.state_dim, self.name)
        F = self.motion.transition_matrix(dt)
        return GaussianState(matmul(F, state.mean.unsqueeze(-1)).squeeze(-1),
                             symmetrize(matmul(F, state.cov) @ F.transpose(-1, -2) + self.motion.process_noise(dt)))

    def _moments(self, state):
        H = self.measurement.matrix()
        C, S = innovation_cov(state.cov, H, self.measurement.noise_cov())
        return matmul(H, state.mean.unsqueeze(-1)).squeeze(-1), S, C

    def _posterior_cov(self, state, gain):
        return joseph_cov(state.cov, gain.gain, self.measurement.matrix(), self.measurement.noise_cov())

    def _small(self) -> bool:
        """Whether the model is small enough for the unrolled per-lane arithmetic of the lanes path."""
        return (self.state_dim <= lanes.MAX_STATE and self.measurement.meas_dim <= lanes.MAX_MEAS
                and type(self.measurement).residual is MeasurementModel.residual)

    def update(self, state: GaussianState, z: Tensor, mask: Tensor | None = None,
               check: bool = True) -> tuple[GaussianState, UpdateInfo]:
        """Joseph-form update (see :meth:`_GaussianFilter.update`). With a shared ``H``, ``R`` and a
        small model it runs in the batch-last layout of :mod:`~torchtrack.filters.kalman.lanes`
        (rank-one updates instead of tiny batched GEMMs; outputs are views of that storage)."""
        H, R = self.measurement.matrix(), self.measurement.noise_cov()
        if not (self._small() and H.dim() == 2 and R.dim() == 2):
            return super().update(state, z, mask, check)
        n, m = self.state_dim, self.measurement.meas_dim
        present, z = self._presence(state, z, mask)
        batch = torch.broadcast_shapes(state.mean.shape[:-1], state.cov.shape[:-2], z.shape[:-1], present.shape)
        B = math.prod(batch)
        u = lanes.update(state.mean.expand(*batch, n).reshape(B, n).transpose(0, 1),
                         state.cov.expand(*batch, n, n).reshape(B, n, n).permute(1, 2, 0),
                         z.expand(*batch, m).reshape(B, m).transpose(0, 1), present.expand(batch).reshape(B), H, R)
        if check and not bool(u.ok.all()):
            raise TorchtrackError(f"{self.name}: innovation covariance S is not positive definite "
                                  f"({int((~u.ok).sum())} of {B} matrices failed Cholesky factorisation)")
        post = GaussianState(u.mean.transpose(0, 1).reshape(*batch, n), u.cov.permute(2, 0, 1).reshape(*batch, n, n))
        info = UpdateInfo(u.innovation.transpose(0, 1).reshape(*batch, m),
                          u.innovation_cov.permute(2, 0, 1).reshape(*batch, m, m), u.nis.reshape(batch),
                          u.log_likelihood.reshape(batch), present.expand(batch))
        return post, info

    def _shared_matrices(self, dt) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """``(F, Q, H, R)`` when all are shared 2-D matrices of a small model (the lanes engine), else None."""
        if not self._small():
            return None
        mats = (self.motion.transition_matrix(dt), self.motion.process_noise(dt), self.measurement.matrix(),
                self.measurement.noise_cov())
        return mats if all(M.dim() == 2 for M in mats) else None

    def _axes_parameters(self, dt) -> tuple[float, float, float, float]:
        """``(q₁₁, q₁₂, q₂₂, r)`` of the axis-decoupled engine, or a clear error where it does not apply."""
        motion, meas = self.motion, self.measurement
        if not isinstance(motion, ConstantVelocity) or not isinstance(meas, LinearPosition) or isinstance(dt, Tensor):
            raise TorchtrackError("Kalman filter engine 'axes' needs ConstantVelocity motion, LinearPosition "
                                  "measurements and a number dt")
        if meas.meas_dim != motion.ndim or meas.state_dim != motion.state_dim:
            raise TorchtrackError("Kalman filter engine 'axes' needs position measurements of every axis")
        sigma = meas.sigma().detach()
        if sigma.numel() != 1 and not bool((sigma == sigma.flatten()[0]).all()):
            raise TorchtrackError("Kalman filter engine 'axes' needs isotropic measurement noise")
        Q = motion.process_noise(dt).detach()
        d = motion.ndim
        return float(Q[0, 0]), float(Q[0, d]), float(Q[d, d]), float(sigma.flatten()[0] ** 2)

    def run(self, measurements: Tensor, init: GaussianState, dt=1.0, mask: Tensor | None = None,
            predict_first: bool = True, compile: bool = False, engine: str = "auto",
            history: bool = True) -> FilterResult:
        """Filter ``measurements (T, *, m)`` (NaN rows or ``mask (T, *)`` = missing); see
        :meth:`_GaussianFilter.run`. Without ``history`` only the last posterior is returned (``T = 1``).

        ``engine`` chooses how the same equations (the shared update of :mod:`torchtrack.gaussian`) are
        laid out; all agree to rounding:

        * ``"batch"``: the batch-first predict/update loop; any linear model, ``dt`` may be a tensor.
        * ``"lanes"``: the batch-last layout of :mod:`~torchtrack.filters.kalman.lanes`; needs shared
          2-D model matrices (``dt`` a number), state size ≤ 8 and measurement size ≤ 4. The returned
          ``mean``/``cov`` are views of batch-last storage (not contiguous).
        * ``"axes"``: the axis-decoupled engine of :mod:`~torchtrack.filters.kalman.axes`; needs
          ``ConstantVelocity`` motion, ``LinearPosition`` measurements of every axis with isotropic
          noise, a number ``dt`` and a prior without cross-axis covariance; NaN marks missing
          measurements per axis. Differentiable in the state, not in the noise parameters (they
          enter as numbers). The fastest for that model.
        * ``"auto"`` (default): ``"lanes"`` where it applies, otherwise ``"batch"``.

        A failed factorisation of ``S`` raises :class:`TorchtrackError` naming the step (lanes: checked
        once, after the last step, so the loop never waits on the host). ``compile=True`` runs each
        step of ``"lanes"`` and ``"axes"`` through ``torch.compile`` when no gradient is needed (one
        fused loop over the tracks; compiled once per process for each model size, dtype and
        with/without missing measurements; falls back to eager where unavailable).
        """
        if engine not in ("auto", "batch", "lanes", "axes"):
            raise TorchtrackError(f"{self.name}: engine must be auto, batch, lanes or axes; got {engine!r}")
        n, m = self.state_dim, self.measurement.meas_dim
        if measurements.dim() < 2 or measurements.shape[-1] != m:
            raise TorchtrackError(f"{self.name}: measurements must have shape (T, *, {m}); got "
                                  f"{tuple(measurements.shape)}")
        _check_state(init, n, self.name)
        if engine == "axes":
            z = measurements if mask is None else torch.where(mask.to(torch.bool).unsqueeze(-1), measurements,
                                                              float("nan"))
            return FilterResult(*kalman_axes.run(z, init.mean, init.cov, float(dt), self._axes_parameters(dt),
                                                 predict_first, compile, history))
        mats = None if engine == "batch" else self._shared_matrices(dt)
        if mats is None:
            if engine == "lanes":
                raise TorchtrackError(f"{self.name}: engine 'lanes' needs shared 2-D model matrices, a number dt, "
                                      f"state size <= {lanes.MAX_STATE} and measurement size <= {lanes.MAX_MEAS}")
            return super().run(measurements, init, dt, mask, predict_first, history)
        T = measurements.shape[0]
        shapes = [measurements.shape[1:-1], init.mean.shape[:-1], init.cov.shape[:-2]]
        if mask is not None:
            shapes.append(mask.shape[1:])
        try:
            batch = torch.broadcast_shapes(*shapes)
        except RuntimeError as err:
            raise TorchtrackError(f"{self.name}: batch shapes of measurements, init and mask do not "
                                  f"broadcast: {[tuple(s) for s in shapes]}") from err
        B = math.prod(batch)
        x = init.mean.expand(*batch, n).reshape(B, n).transpose(0, 1).contiguous()
        P = init.cov.expand(*batch, n, n).reshape(B, n, n).permute(1, 2, 0).contiguous()
        z = measurements.expand(T, *batch, m).reshape(T, B, m)
        present = ~torch.isnan(z).any(-1)
        if mask is not None:
            present = present & mask.expand(T, *batch).reshape(T, B).to(torch.bool)
        all_present = bool(present.all())
        if not all_present:                                      # zero-filled only where needed (one pass less)
            z = torch.where(present.unsqueeze(-1), z, 0.0)
        z = z.transpose(1, 2).contiguous()                                              # (T, m, B)
        needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (x, P, z, *mats))
        if compile and not needs_grad:
            mean, cov, nis, total, ok = self._run_compiled(x, P, z, None if all_present else present, mats,
                                                           predict_first, history)
        else:
            steps, oks = [], []
            total = torch.zeros(B, dtype=z.dtype, device=z.device)
            for k in range(T):
                x, P, nis_k, ll_k, ok_k = lanes.step(x, P, z[k], None if all_present else present[k], *mats,
                                                     predict_first or k > 0)
                if history or k == T - 1:
                    steps.append((x, P, nis_k))
                oks.append(ok_k)
                total = total + ll_k
            mean, cov, nis = (torch.stack(t) for t in zip(*steps))
            ok = torch.stack(oks)
        failed = ~ok                                                 # (T, B); the one host sync
        if bool(failed.any()):
            k = int(failed.any(-1).nonzero()[0])
            raise TorchtrackError(f"{self.name}: innovation covariance S is not positive definite at step {k} "
                                  f"({int(failed[k].sum())} of {B} matrices failed Cholesky factorisation)")
        Tk = mean.shape[0]
        return FilterResult(mean.permute(0, 2, 1).reshape(Tk, *batch, n),
                            cov.permute(0, 3, 1, 2).reshape(Tk, *batch, n, n), nis.reshape(Tk, *batch),
                            total.reshape(batch))

    @staticmethod
    def _run_compiled(x: Tensor, P: Tensor, z: Tensor, present: Tensor | None, mats, predict_first: bool,
                      history: bool = True):
        """The time loop through the compiled :func:`~torchtrack.filters.kalman.lanes.fused_step`, which
        writes each posterior straight into the batch-last history (no autograd); without ``history``
        two slots are used in turn and the last is returned."""
        (n, B), T = x.shape, z.shape[0]
        slots = T if history else 2
        mean, cov, nis = x.new_empty(slots, n, B), P.new_empty(slots, n, n, B), x.new_empty(slots, B)
        ok = torch.empty(T, B, dtype=torch.bool, device=x.device)
        total = x.new_zeros(B)
        pattern = tuple(lanes.structure(M) for M in mats)
        for k in range(T):
            prev = (x, P) if k == 0 else (mean[(k - 1) % slots], cov[(k - 1) % slots])
            lanes.compiled_step(*prev, z[k], None if present is None else present[k], *mats, mean[k % slots],
                                cov[k % slots], nis[k % slots], total, ok[k], predict_first or k > 0, pattern)
        if not history:
            last = (T - 1) % slots
            mean, cov, nis = mean[last:last + 1], cov[last:last + 1], nis[last:last + 1]
        return mean, cov, nis, total, ok


class ExtendedKalmanFilter(_GaussianFilter):
    """Extended Kalman filter: linearisation by the models' Jacobians (autograd where none is given)."""

    name = "extended Kalman filter"

    def predict(self, state: GaussianState, dt=1.0) -> GaussianState:
        _check_state(state, self.state_dim, self.name)
        F = self.motion.jacobian(state.mean, dt)
        return GaussianState(self.motion.transition(state.mean, dt),
                             symmetrize(F @ state.cov @ F.transpose(-1, -2) + self.motion.process_noise(dt)))

    def _moments(self, state):
        C, S = innovation_cov(state.cov, self.measurement.jacobian(state.mean), self.measurement.noise_cov())
        return self.measurement.measure(state.mean), S, C

    def _posterior_cov(self, state, gain):
        return joseph_cov(state.cov, gain.gain, self.measurement.jacobian(state.mean), self.measurement.noise_cov())


class UnscentedKalmanFilter(_GaussianFilter):
    """Unscented Kalman filter with the scaled sigma points of Wan & van der Merwe (2000).

    ``2n + 1`` points ``x ± √((n + λ) P)`` columns, ``λ = α² (n + κ) − n``; weights
    ``W_m0 = λ / (n + λ)``, ``W_c0 = W_m0 + 1 − α² + β``, others ``1 / (2 (n + λ))``.
    Angular measurement residuals are wrapped by the measurement model's ``residual``.
    """

    name = "unscented Kalman filter"

    def __init__(self, motion: MotionModel, measurement: MeasurementModel, alpha: float = 1.0,
                 beta: float = 2.0, kappa: float = 0.0):
        super().__init__(motion, measurement)
        n = motion.state_dim
        self.lam = alpha**2 * (n + kappa) - n
        if n + self.lam <= 0:
            raise TorchtrackError(f"UKF: n + lambda must be > 0 (alpha={alpha}, kappa={kappa})")
        w = 1.0 / (2 * (n + self.lam))
        wm = [self.lam / (n + self.lam)] + [w] * (2 * n)
        wc = [wm[0] + 1 - alpha**2 + beta] + [w] * (2 * n)
        self.register_buffer("wm", torch.tensor(wm, dtype=torch.float64), persistent=False)
        self.register_buffer("wc", torch.tensor(wc, dtype=torch.float64), persistent=False)

    def _sigma_points(self, state: GaussianState) -> Tensor:
        n = self.state_dim
        L = cholesky((n + self.lam) * state.cov, f"{self.name}: state covariance")
        cols = L.transpose(-1, -2)  # rows are columns of L
        x = state.mean.unsqueeze(-2)
        return torch.cat([x, x + cols, x - cols], -2)  # (*, 2n+1, n)

    def predict(self, state: GaussianState, dt=1.0) -> GaussianState:
        _check_state(state, self.state_dim, self.name)
        pts = self.motion.transition(self._sigma_points(state), dt)
        wm, wc = self.wm.to(pts), self.wc.to(pts)
        mean = (wm.unsqueeze(-1) * pts).sum(-2)
        d = pts - mean.unsqueeze(-2)
        cov = (wc[:, None, None] * d.unsqueeze(-1) * d.unsqueeze(-2)).sum(-3)
        return GaussianState(mean, symmetrize(cov + self.motion.process_noise(dt)))

    def _moments(self, state):
        pts = self._sigma_points(state)
        zs = self.measurement.measure(pts)
        wm, wc = self.wm.to(pts), self.wc.to(pts)
        # mean of angles: average residuals about the central point so wrapping stays consistent
        z0 = zs[..., 0:1, :]
        dz0 = self.measurement.residual(zs, z0)
        z_hat = z0.squeeze(-2) + (wm.unsqueeze(-1) * dz0).sum(-2)
        dz = self.measurement.residual(zs, z_hat.unsqueeze(-2))
        dx = pts - state.mean.unsqueeze(-2)
        S = (wc[:, None, None] * dz.unsqueeze(-1) * dz.unsqueeze(-2)).sum(-3) + self.measurement.noise_cov()
        C = (wc[:, None, None] * dx.unsqueeze(-1) * dz.unsqueeze(-2)).sum(-3)
        return z_hat, symmetrize(S), C


def nees(state: GaussianState, truth: Tensor) -> Tensor:
    """Normalised estimation error squared ``(x − x̂)ᵀ P⁻¹ (x − x̂)``, shape ``(*,)``."""
    return mahalanobis_sq(truth, state.mean, cholesky(state.cov, "state covariance"))


def chi2_bounds(dof: int, runs: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval for the average of ``runs`` χ²(``dof``) values (consistency tests)."""
    a = (1 - prob) / 2
    return chi2_quantile(a, dof * runs) / runs, chi2_quantile(1 - a, dof * runs) / runs


__all__ = [
    "ExtendedKalmanFilter", "FilterResult", "GaussianState", "KalmanFilter", "UnscentedKalmanFilter",
    "UpdateInfo", "chi2_bounds", "nees",
]
