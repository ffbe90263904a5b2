"""The axis-decoupled engine of :meth:`KalmanFilter.run <torchtrack.filters.kalman.filter.KalmanFilter.run>`
(``engine="axes"``), for the commonest tracking model: nearly constant velocity with position
measurements and isotropic noise.

With state ``[p (d), v (d)]``, ``F = [[1, T], [0, 1]] ⊗ I_d``, ``Q = q Q₁(T) ⊗ I_d``, ``H = [I_d 0]``
and ``R = r I_d``, the filter separates into ``d`` identical, independent two-state filters, one per
axis, each with a scalar measurement. Keeping the three distinct entries of each axis covariance
``[[a, b], [b, c]]`` turns the whole filter into elementwise arithmetic over ``tracks × axes`` lanes,
which ``torch.compile`` fuses into one loop per step (memory bound). The update is the shared one of
:mod:`torchtrack.gaussian` with ``m = 1`` (``C = P Hᵀ = [a, b]ᵀ``)::

    predict   p ← p + T v
              a ← a + 2T b + T² c + q₁₁,  b ← b + T c + q₁₂,  c ← c + q₂₂
    update    L = √(a + r),  ŵ = (z − p) / L,  W = [a, b]ᵀ / L         (cholesky_entries, solve_lower_entries)
              p ← p + W_p ŵ,  v ← v + W_v ŵ
              a ← a − W_p²,  b ← b − W_p W_v,  c ← c − W_v²          (P − W Wᵀ)
              NIS = ŵ²,  log ℓ = −½ (ŵ² + 2 log L + log 2π)          (gaussian_log_likelihood)

Equal (to rounding) to the general engines on that model: the tests check it. Cross-axis covariance
terms must be zero (they stay zero).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.filters.kalman.lanes import Compiled
from torchtrack.gaussian import cholesky_entries, gaussian_log_likelihood, solve_lower_entries


class AxisState(NamedTuple):
    """Per-lane (track × axis) state of the decoupled filter; every tensor has shape ``(*, d)``."""

    p: Tensor
    v: Tensor
    a: Tensor   # var(p)
    b: Tensor   # cov(p, v)
    c: Tensor   # var(v)


def predict(s: AxisState, dt: float, q11: float, q12: float, q22: float) -> AxisState:
    p, v, a, b, c = s
    return AxisState(p + dt * v, v, a + 2 * dt * b + dt * dt * c + q11, b + dt * c + q12, c + q22)


def update(s: AxisState, z: Tensor, r: float) -> tuple[AxisState, Tensor, Tensor]:
    """Scalar-measurement update of every lane with ``z (*, d)``, NaN = missing (the lane passes
    through, NIS and log ℓ 0); returns the posterior, the NIS and log ℓ per lane."""
    p, v, a, b, c = s
    present = ~torch.isnan(z)
    L, _ = cholesky_entries([[a + r]])                    # a + r > 0: r > 0 and a ≥ 0
    white = solve_lower_entries(L, [torch.where(present, z - p, 0.0)])[0]
    wp, wv = solve_lower_entries(L, [a])[0], solve_lower_entries(L, [b])[0]
    wp, wv = torch.where(present, wp, 0.0), torch.where(present, wv, 0.0)
    nis = white * white
    loglik = torch.where(present, gaussian_log_likelihood(nis, 2.0 * torch.log(L[0][0]), 1), 0.0)
    return AxisState(p + wp * white, v + wv * white, a - wp * wp, b - wp * wv, c - wv * wv), nis, loglik


def _step(p, v, a, b, c, ll, z, dt: float, q11: float, q12: float, q22: float, r: float):
    """:func:`predict` then :func:`update`, flat arguments (what ``torch.compile`` fuses into one loop);
    returns the posterior lanes, ``ll`` plus this step's log ℓ, and the NIS."""
    s, nis_k, ll_k = update(predict(AxisState(p, v, a, b, c), dt, q11, q12, q22), z, r)
    return (*s, ll + ll_k, nis_k)


compiled_step = Compiled(_step, "the Kalman filter engine 'axes'", dynamic=False, fullgraph=True)


def split_axes(mean: Tensor, cov: Tensor) -> AxisState:
    """Per-axis entries of a ``[p (d), v (d)]`` Gaussian; cross-axis covariances must be zero."""
    d = mean.shape[-1] // 2
    idx = torch.arange(d, device=cov.device)
    a, b, c = cov[..., idx, idx], cov[..., idx, idx + d], cov[..., idx + d, idx + d]
    s = AxisState(mean[..., :d], mean[..., d:], a, b, c)
    rebuilt = merge_axes(s)[1]
    if not torch.allclose(rebuilt, cov.expand_as(rebuilt)):
        raise TorchtrackError("Kalman filter engine 'axes': the initial covariance must have no cross-axis terms")
    return s


def merge_axes(s: AxisState) -> tuple[Tensor, Tensor]:
    """The full ``[p, v]`` mean ``(*, 2d)`` and covariance ``(*, 2d, 2d)``."""
    a, b, c = torch.broadcast_tensors(s.a, s.b, s.c)
    eye = torch.eye(s.p.shape[-1], dtype=a.dtype, device=a.device)
    top = torch.cat([a[..., :, None] * eye, b[..., :, None] * eye], -1)
    bottom = torch.cat([b[..., :, None] * eye, c[..., :, None] * eye], -1)
    return torch.cat([s.p, s.v], -1), torch.cat([top, bottom], -2)


def run(measurements: Tensor, mean: Tensor, cov: Tensor, dt: float, params: tuple[float, float, float, float],
        predict_first: bool = True, compile: bool = False, history: bool = True
        ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Filter ``measurements (T, *, d)`` (NaN = missing) from the prior ``mean (*, 2d)``, ``cov (*, 2d, 2d)``
    with ``params = (q₁₁, q₁₂, q₂₂, r)``; returns ``mean (T', *, 2d)``, ``cov (T', *, 2d, 2d)``,
    ``nis (T', *)`` and the total log-likelihood ``(*,)``, with ``T' = T`` (or 1 without ``history``:
    the last step only). ``compile`` uses ``torch.compile`` where available."""
    q11, q12, q22, r = params
    s = split_axes(mean, cov)
    batch = torch.broadcast_shapes(measurements.shape[1:], *(t.shape for t in s))
    state = [t.expand(batch).contiguous() for t in s]
    ll = torch.zeros(batch, dtype=measurements.dtype, device=measurements.device)
    step = compiled_step if compile else _step
    steps = []
    for k in range(measurements.shape[0]):
        if predict_first or k > 0:
            *state, ll, nis = step(*state, ll, measurements[k], dt, q11, q12, q22, r)
        else:
            post, nis, ll_k = update(AxisState(*state), measurements[k], r)
            state, ll = list(post), ll + ll_k
        if history or k == measurements.shape[0] - 1:
            steps.append((*merge_axes(AxisState(*state)), nis.sum(-1)))
    mean, cov, nis = (torch.stack(t) for t in zip(*steps))
    return mean, cov, nis, ll.sum(-1)
