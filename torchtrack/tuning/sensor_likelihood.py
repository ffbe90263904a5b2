"""The multi-object likelihood of each frame's detections given smoothed track states, maximised by gradient
(the M-step of :mod:`torchtrack.tuning.calibrate`; docs/calibrate.md, "The likelihood").

Given the states of the tracks alive at frame ``k`` (each the leave-one-out predictive ``N(μ_i, A_i)`` of its
detection, :mod:`torchtrack.tuning.track_smoother`), the detections ``Z_k`` are the union of a Poisson clutter
process of intensity ``c(z, v) = κ N(v; 0, τ² I)`` and, for each track, a Bernoulli detection of probability
``p_D`` and density ``g_i(z, v) = N([z, v]; μ_i, A_i + R)``, ``R = diag(σ², σ², σ_v², σ_v²)``. With the tracks'
gates disjoint the association sums out exactly (the PMB update's Bernoulli factor, Williams 2015, eq. 35)::

    log p(Z_k) = −κ |A| + Σ_j log c(z_j) + Σ_i log[(1 − p_D) + p_D Σ_{j ∈ gate(i)} g_i(z_j) / c_i(z_j)]

with ``c_i = c``. Where gates overlap (vehicles parked a few px apart), a detection that another track explains
is not clutter to track ``i``: ``c_i(z_j) = c(z_j) + Σ_{i' ≠ i} w_{i'} g_{i'}(z_j)`` (``w = p_D``; the
other tracks' Poisson approximation, as in the PHD update, Mahler 2003, eq. 72), so that a neighbour's
detection does not widen σ or stand in for a missed detection. The other tracks' term is evaluated once, at
the E-step's sensor (:func:`other_tracks`), and held through the M-step like the tracks' states.

A track's first and last detected frames are conditioned on a detection (the tracker found the track there),
so their factor is ``Σ_j g_i(z_j) / c(z_j)`` without ``p_D``: p_D counts only the frames strictly inside a
track's life. κ and τ are measured apart, where no track passes (:mod:`torchtrack.tuning.background`), and held
here; σ, p_D and σ_v are fitted in unconstrained form (log σ, logit p_D, log σ_v) by L-BFGS in float64;
standard errors are the delta method on the Cholesky factor of the Hessian of the negative log-likelihood.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

NAMES_POSITION = ("sigma", "p_detection")
NAMES_VELOCITY = NAMES_POSITION + ("velocity_sigma",)


@dataclass
class SensorPairs:
    """The data of the likelihood: ``log_clutter (P,)`` the clutter's log-intensity ``log c(z_j)`` at each
    candidate pair's detection; per track-frame ``(M,)``: ``endpoint`` (bool), ``loo_cov (M, m, m)``; per
    candidate pair ``(P,)``: ``track_frame`` (index into the M track-frames), ``detection`` (index of the
    detection among the candidates' detections), ``residual (P, m)`` (detection minus ``μ``). The terms
    without σ, p_D, σ_v are left out."""

    log_clutter: Tensor
    endpoint: Tensor
    loo_cov: Tensor
    track_frame: Tensor
    detection: Tensor
    residual: Tensor
    others: Tensor | None = None

    @property
    def velocities(self) -> bool:
        return self.residual.shape[-1] == 4


LOG_NOISE = (math.log(0.02), math.log(100.0))
"""Bounds of log σ and log σ_v (px, px/frame) that keep an L-BFGS line search's trial points finite."""


def _values(theta: Tensor, velocities: bool) -> dict[str, Tensor]:
    out = {"sigma": theta[0].clamp(*LOG_NOISE).exp(), "p_detection": torch.sigmoid(theta[1].clamp(-20, 20))}
    if velocities:
        out["velocity_sigma"] = theta[2].clamp(*LOG_NOISE).exp()
    return out


def to_theta(values: dict[str, float], velocities: bool) -> Tensor:
    """Unconstrained parameters of ``values`` (the inverse of the fitted transform)."""
    pd = min(max(values["p_detection"], 1e-4), 1 - 1e-4)
    t = [math.log(values["sigma"]), math.log(pd / (1 - pd))]
    if velocities:
        t += [math.log(values["velocity_sigma"])]
    return torch.tensor(t, dtype=torch.float64)


def _log_g(theta: Tensor, data: SensorPairs) -> Tensor:
    v = _values(theta, data.velocities)
    m = data.loo_cov.shape[-1]
    noise = [v["sigma"] ** 2] * 2 + ([v["velocity_sigma"] ** 2] * 2 if m == 4 else [])
    C = data.loo_cov + torch.diag_embed(torch.stack(noise)).expand_as(data.loo_cov)
    L = torch.linalg.cholesky(C)
    Lp = L[data.track_frame]
    w = torch.linalg.solve_triangular(Lp, data.residual.unsqueeze(-1), upper=False).squeeze(-1)
    log_det = 2 * torch.log(torch.diagonal(Lp, dim1=-2, dim2=-1)).sum(-1)
    return -0.5 * ((w ** 2).sum(-1) + log_det + m * math.log(2 * math.pi))


def other_tracks(theta: Tensor, data: SensorPairs) -> Tensor:
    """``Σ_{i' ≠ i} w_{i'} g_{i'}(z_j)`` for each candidate pair ``(i, j)`` at ``theta`` (module docstring)."""
    with torch.no_grad():
        pd = _values(theta, data.velocities)["p_detection"]
        w = torch.where(data.endpoint[data.track_frame], torch.ones_like(pd), pd) * _log_g(theta, data).exp()
        total = torch.zeros(int(data.detection.max()) + 1, dtype=w.dtype).index_add(0, data.detection, w)
        return (total[data.detection] - w).clamp_min(0.0)


def log_likelihood(theta: Tensor, data: SensorPairs) -> Tensor:
    """The log-likelihood (module docstring) of the whole window at unconstrained ``theta``."""
    pd = _values(theta, data.velocities)["p_detection"]
    log_g = _log_g(theta, data)
    log_c = data.log_clutter if data.others is None else torch.logaddexp(data.log_clutter, torch.log(data.others))
    ratio = log_g - log_c
    M = data.endpoint.shape[0]
    peak = torch.full((M,), -torch.inf, dtype=ratio.dtype).scatter_reduce(0, data.track_frame, ratio.detach(),
                                                                           "amax")
    peak = torch.where(torch.isfinite(peak), peak, torch.zeros_like(peak))
    summed = torch.zeros(M, dtype=ratio.dtype).index_add(0, data.track_frame, (ratio - peak[data.track_frame]).exp())
    has = summed > 0                                                     # a candidate in the gate
    log_sum = torch.log(torch.where(has, summed, torch.ones_like(summed))) + peak      # log Σ_j g/c_i
    miss = torch.log1p(-pd).expand_as(log_sum)
    inner = torch.where(has, torch.logaddexp(miss, torch.log(pd) + log_sum), miss)
    ends = torch.where(has, log_sum, torch.zeros_like(log_sum))
    return torch.where(data.endpoint, ends, inner).sum()


@dataclass
class SensorEstimate:
    """Fitted values, their standard errors (delta method), the log-likelihood before and after, and the
    negative log-likelihood per candidate pair at each L-BFGS iteration."""

    values: dict[str, float]
    stderr: dict[str, float]
    loglik_before: float
    loglik_after: float
    trace: list[float]


def fit_sensor_likelihood(data: SensorPairs, start: dict[str, float], iterations: int = 50,
                          rounds: int = 6) -> SensorEstimate:
    """Maximise :func:`log_likelihood` from ``start`` by L-BFGS (strong Wolfe line search), restarted up to
    ``rounds`` times while it still gains."""
    theta = to_theta(start, data.velocities).requires_grad_(True)
    scale = float(max(data.residual.shape[0], 1))
    with torch.no_grad():
        before = float(log_likelihood(theta, data))
    trace = [-before / scale]

    def closure() -> Tensor:
        opt.zero_grad()
        loss = -log_likelihood(theta, data) / scale
        loss.backward()
        trace.append(float(loss.detach()))
        return loss

    for _ in range(rounds):                 # L-BFGS stops early on a flat start; restart it until it settles
        opt = torch.optim.LBFGS([theta], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-9, tolerance_change=1e-12)
        best = min(trace)
        opt.step(closure)
        if best - min(trace) < 1e-7:
            break
    theta = theta.detach()
    after = float(log_likelihood(theta, data))
    return SensorEstimate(_as_floats(_values(theta, data.velocities)), _stderr(theta, data), before, after, trace)


def _as_floats(values: dict[str, Tensor]) -> dict[str, float]:
    return {k: float(x) for k, x in values.items()}


def _stderr(theta: Tensor, data: SensorPairs) -> dict[str, float]:
    """Delta-method standard errors: ``J H⁻¹ Jᵀ`` with ``H`` the Hessian of the negative log-likelihood in
    ``theta`` (through its Cholesky factor) and ``J`` the transform's Jacobian (diagonal here)."""
    H = torch.autograd.functional.hessian(lambda t: -log_likelihood(t, data), theta)
    L, info = torch.linalg.cholesky_ex(0.5 * (H + H.T))
    names = NAMES_VELOCITY if data.velocities else NAMES_POSITION
    if int(info) != 0:
        return {k: math.nan for k in names}
    var = torch.cholesky_solve(torch.eye(len(theta), dtype=theta.dtype), L).diagonal()
    th = theta.clone().requires_grad_(True)
    vals = _values(th, data.velocities)
    out = {}
    for i, k in enumerate(names):
        (grad,) = torch.autograd.grad(vals[k], th)
        out[k] = float(grad[i].abs() * var[i].sqrt())
    return out
