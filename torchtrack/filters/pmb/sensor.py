"""TOMB/P tracking from a sensor whose own state is uncertain (Fröhle, Granström & Wymeersch 2018).

The vehicle (sensor) state ``x ~ N(μ_x, Σ_x)`` moves by its own linear model (eq. 1) and is measured by
GNSS, ``z_G = H_G x + r`` (eq. 3). Features ``f`` are measured relative to it (eq. 4)::

    z = H_2 f − H_1 x + q,  q ~ N(0, Q)          (H_1 = H_2 = [I 0]: position blocks)

(the paper writes ``z = H_1 x + H_2 f + q`` with ``H_2 = −H_1``; we use feature-minus-sensor, the sign
being a convention). Three ways of tracking the features in the global frame share the
:class:`~torchtrack.filters.pmb.filter.PMBFilter` code:

* **naive** — the sensor is where its position estimate ``μ`` says: measurements ``z + H_1 μ`` with
  noise ``Q`` (:func:`v2f_update` with ``sensor_cov=None``);
* **variance inflation** (Sec. 3.4) — the same measurements with noise ``Q + H_1 Σ_x H_1ᵀ``
  (:func:`v2f_update` with the sensor covariance);
* **joint** (Sec. 4, [1]) — :class:`JointSensorPMB`: the prior is the product ``p(x) f(F)`` (eq. 5);
  prediction and the GNSS Kalman update act on ``p(x)`` alone (eq. 6); for a V2F scan each
  single-target hypothesis ``(i, j)`` is a Kalman update of the **joint** Gaussian of ``(x, f_i)``
  with ``H = [−H_1, H_2]``. Its feature marginal has innovation covariance
  ``H_2 P_i H_2ᵀ + H_1 Σ_x H_1ᵀ + Q``, the one of variance inflation, so the feature part is the
  TOMB/P update above. The vehicle marginal of the association mixture (eq. 7) is brought back to
  one Gaussian — the approximation that keeps the density in the product form (5), so the cost does
  not grow over time. Given the association, the V2F measurements are independent pseudo-measurements
  of the vehicle, ``y_ij = H_2 m_i − z_j = H_1 x + e``, ``e ~ N(0, U_i)``, ``U_i = H_2 P_i H_2ᵀ + Q``;
  we weight each by its marginal association probability ``β_ij = p_i(j)`` and add the information::

      Λ = Σ_i β_i U_i⁻¹,  b = Σ_i U_i⁻¹ Σ_j β_ij y_ij,  β_i = Σ_j β_ij
      p(x | Z) ≈ Kalman update of p(x) with ȳ = Λ⁻¹ b, noise Λ⁻¹      (information form)

  The cross-covariance between vehicle and features created by each update is dropped (product
  form), as in the paper; new Bernoullis, born from the broad Poisson intensity, carry no information
  about the vehicle and are left out of the vehicle update.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb.filter import PMBFilter, PMBState, PMBUpdateInfo
from torchtrack.gaussian import chol_solve, cholesky, kalman_update, symmetrize
from torchtrack.models.motion import MotionModel


class SensorState(NamedTuple):
    """Gaussian vehicle (sensor) state, batch ``*``."""

    mean: Tensor  # (*, n_s)
    cov: Tensor   # (*, n_s, n_s)


def v2f_update(pmb: PMBFilter, state: PMBState, z_rel: Tensor, mask: Tensor | None, sensor_mean: Tensor,
               sensor_cov: Tensor | None = None) -> tuple[PMBState, PMBUpdateInfo]:
    """TOMB/P update with relative measurements from a sensor at ``sensor_mean`` (naive / inflated).

    ``z_rel (*, M, d)`` are ``H_2 f − H_1 x + q``; ``sensor_mean (*, n_s)`` (or ``(*, d)``) the sensor
    estimate; ``sensor_cov (*, n_s, n_s)`` (or ``(*, d, d)``) its covariance for variance inflation,
    ``None`` to ignore it. A sensor covariance that is not positive definite is a
    :class:`TorchtrackError` (positive semi-definite with zeros is allowed through ``Q``).
    """
    d = z_rel.shape[-1]
    shift = sensor_mean[..., :d].to(z_rel)
    extra = None
    if sensor_cov is not None:
        extra = symmetrize(sensor_cov[..., :d, :d].to(z_rel))
        _check_sensor_cov(extra)
    return pmb.update(state, z_rel + shift.unsqueeze(-2), mask, extra_noise=extra)


def _check_sensor_cov(P: Tensor) -> None:
    if not bool(torch.isfinite(P).all()):
        raise TorchtrackError("sensor covariance contains NaN or infinite entries")
    eig = torch.linalg.eigvalsh(P.detach())
    if bool((eig < -1e-9 * eig.abs().amax(-1, keepdim=True).clamp_min(1.0)).any()):
        raise TorchtrackError("sensor covariance is not positive semi-definite")


class JointSensorPMB(nn.Module):
    """The joint vehicle–feature PMB filter (module docstring).

    Args:
        pmb: the feature filter (global frame).
        sensor_motion: linear motion model of the vehicle.
        gnss_sigma: GNSS position noise standard deviation (``R = σ² I``).
    """

    def __init__(self, pmb: PMBFilter, sensor_motion: MotionModel, gnss_sigma: float):
        super().__init__()
        self.pmb = pmb
        self.sensor_motion = sensor_motion
        self.register_buffer("gnss_var", torch.tensor(float(gnss_sigma) ** 2))

    def predict(self, sensor: SensorState, state: PMBState, dt) -> tuple[SensorState, PMBState]:
        """Chapman–Kolmogorov on vehicle and features separately (the product form is kept)."""
        F = self.sensor_motion.transition_matrix(dt).to(sensor.mean)
        Q = self.sensor_motion.process_noise(dt).to(sensor.mean)
        mean = (F @ sensor.mean.unsqueeze(-1)).squeeze(-1)
        cov = symmetrize(F @ sensor.cov @ F.transpose(-1, -2) + Q)
        return SensorState(mean, cov), self.pmb.predict(state, dt)

    def gnss_update(self, sensor: SensorState, z_gnss: Tensor, mask: Tensor | None = None) -> SensorState:
        """Kalman update of the vehicle by a GNSS fix ``z_gnss (*, d)`` (eq. 6); ``mask (*,)`` False skips."""
        d = z_gnss.shape[-1]
        H = torch.eye(d, sensor.mean.shape[-1], dtype=sensor.mean.dtype, device=sensor.mean.device)   # [I 0]
        R = self.gnss_var.to(sensor.mean) * torch.eye(d, dtype=sensor.mean.dtype, device=sensor.mean.device)
        upd = kalman_update(sensor.mean, sensor.cov, z_gnss.to(sensor.mean), H, R)
        if mask is None:
            return SensorState(upd.mean, upd.cov)
        m = mask.bool()
        return SensorState(torch.where(m.unsqueeze(-1), upd.mean, sensor.mean),
                           torch.where(m[..., None, None], upd.cov, sensor.cov))

    def v2f_update(self, sensor: SensorState, state: PMBState, z_rel: Tensor, mask: Tensor | None = None
                   ) -> tuple[SensorState, PMBState, PMBUpdateInfo]:
        """Joint update by one V2F scan ``z_rel (*, M, d)``; returns vehicle, features and the update info."""
        new_state, info = v2f_update(self.pmb, state, z_rel, mask, sensor.mean, sensor.cov)
        d = z_rel.shape[-1]
        ref = sensor.mean
        H2 = self.pmb.measurement.matrix().to(ref)                               # (d, n_f)
        Q = self.pmb.measurement.noise_cov().to(ref)
        U = symmetrize(H2 @ state.cov @ H2.transpose(-1, -2) + Q)                # (*, N, d, d)
        LU = cholesky(U, "joint PMB: vehicle pseudo-measurement covariance")
        eye = torch.eye(d, dtype=ref.dtype, device=ref.device)
        beta = info.marginals.assoc_matrix()                                     # (*, N, M)
        y = (state.mean @ H2.transpose(-1, -2)).unsqueeze(-2) - z_rel.to(ref).unsqueeze(-3)  # (*, N, M, d)
        ybar = (beta.unsqueeze(-1) * y).sum(-2)                                  # Σ_j β_ij y_ij
        Uinv = chol_solve(LU, eye.expand_as(LU))
        info_mat = (beta.sum(-1)[..., None, None] * Uinv).sum(-3)               # Λ (*, d, d)
        info_vec = chol_solve(LU, ybar.unsqueeze(-1)).squeeze(-1).sum(-2)       # b (*, d)
        # Λ may be 0 (nothing detected): a tiny ridge makes the pseudo-measurement uninformative
        ridge = torch.finfo(ref.dtype).eps ** 0.5 * eye
        LL = cholesky(symmetrize(info_mat) + ridge, "joint PMB: vehicle information matrix")
        y_comb = chol_solve(LL, info_vec.unsqueeze(-1)).squeeze(-1)
        R_comb = symmetrize(chol_solve(LL, eye.expand_as(LL)))
        H1 = torch.eye(d, ref.shape[-1], dtype=ref.dtype, device=ref.device)   # [I 0]: the vehicle's position
        upd = kalman_update(sensor.mean, sensor.cov, y_comb, H1, R_comb)
        return SensorState(upd.mean, upd.cov), new_state, info
