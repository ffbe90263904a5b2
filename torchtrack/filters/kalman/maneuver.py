"""Maneuver detection by the chi-square test on the normalised innovation, with reset.

The maneuver paper (Prabha, Supriya & Pillai, §3.3 and §4.1): at each scan compute

    d²_k = ν_kᵀ S_k⁻¹ ν_k,   ν_k = z_k − H x̂⁻_k,   S_k = H P⁻_k Hᵀ + R             (20), (21)

which is χ²-distributed with ``m`` degrees of freedom when the model holds. When ``d²_k`` exceeds a
threshold (the paper: 10, ≈ the 0.99 quantile for m = 2) a maneuver is declared, the filter is reset
and re-initialised from the last two measurements (two-point differencing, Bar-Shalom et al. 2001,
§5.5.3)::

    x = [z_k, (z_k − z_{k−1}) / T],   P = [[R, R/T], [R/T, 2R/T²]]

Every track/run of the batch tests and resets independently (``torch.where``; no loop over tracks).
The state layout must be ``[p (m), v (m)]`` with position measurements (``LinearPosition``).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter
from torchtrack.gaussian import chi2_quantile


class ManeuverResult(NamedTuple):
    """A filtered sequence with the maneuver test (``T`` scans, batch ``*``)."""

    mean: Tensor            # (T, *, n) posterior means (NaN-free; before the first two scans: the prior)
    cov: Tensor             # (T, *, n, n)
    d2: Tensor              # (T, *) normalised innovation squared (0 where not tested)
    detected: Tensor        # (T, *) bool, a maneuver declared (and the filter reset) at this scan
    log_likelihood: Tensor  # (*,) Σ log N(ν; 0, S) over tested scans


def two_point_init(z_prev: Tensor, z: Tensor, R: Tensor, dt: float) -> GaussianState:
    """Two-point differencing initialisation from ``z_prev, z (*, m)`` and ``R (m, m)``."""
    cov = torch.cat([torch.cat([R, R / dt], -1), torch.cat([R / dt, 2 * R / dt**2], -1)], -2)
    return GaussianState(torch.cat([z, (z - z_prev) / dt], -1), cov.expand(*z.shape[:-1], *cov.shape))


class ManeuverDetectingKalmanFilter(nn.Module):
    """A Kalman filter that declares a maneuver when ``d² > threshold`` and re-initialises.

    ``threshold`` is a value (the paper: 10); alternatively give ``probability`` (e.g. 0.99) and the
    χ² quantile with ``m`` degrees of freedom is used. ``reset=False`` gives the plain filter with
    the same test recorded (for comparisons).
    """

    def __init__(self, kf: KalmanFilter, threshold: float | None = 10.0, probability: float | None = None,
                 reset: bool = True):
        super().__init__()
        m, n = kf.measurement.meas_dim, kf.state_dim
        if n != 2 * m:
            raise TorchtrackError(f"maneuver detection needs a [p (m), v (m)] state with position measurements; "
                                  f"got state size {n} and measurement size {m}")
        if probability is not None:
            threshold = chi2_quantile(probability, m)
        if threshold is None or threshold <= 0:
            raise TorchtrackError(f"threshold must be > 0; got {threshold}")
        self.kf = kf
        self.threshold = float(threshold)
        self.reset = reset

    def run(self, measurements: Tensor, dt: float = 1.0) -> ManeuverResult:
        """Filter ``measurements (T, *, m)``; the filter starts by two-point differencing at scan 1.

        Scan 0 only stores its measurement; from scan 2 on each scan predicts, tests, and either
        updates or (on detection) re-initialises from scans ``k−1, k``.
        """
        T = measurements.shape[0]
        if T < 2:
            raise TorchtrackError(f"maneuver detection needs at least 2 scans; got {T}")
        if bool(torch.isnan(measurements).any()):
            raise TorchtrackError("maneuver detection does not accept missing (NaN) measurements")
        R = self.kf.measurement.noise_cov().to(measurements)
        state = two_point_init(measurements[0], measurements[1], R, dt)
        batch = measurements.shape[1:-1]
        zeros = torch.zeros(batch, dtype=measurements.dtype, device=measurements.device)
        no = torch.zeros(batch, dtype=torch.bool, device=measurements.device)
        steps = [(state.mean, state.cov, zeros, no)] * 2
        total = zeros
        for k in range(2, T):
            state, info = self.kf.update(self.kf.predict(state, dt), measurements[k])
            total = total + info.log_likelihood
            detected = info.nis > self.threshold
            if self.reset:
                fresh = two_point_init(measurements[k - 1], measurements[k], R, dt)
                state = GaussianState(torch.where(detected.unsqueeze(-1), fresh.mean, state.mean),
                                      torch.where(detected[..., None, None], fresh.cov, state.cov))
            steps.append((state.mean, state.cov, info.nis, detected))
        return ManeuverResult(*(torch.stack(t) for t in zip(*steps)), total)
