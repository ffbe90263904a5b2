"""The gate paper's ground formation (§5): truth, detections with class reports, and classified clutter.

Targets start on a vertical line, ``separation`` metres apart, and move left to right (+x) at
``speed``; the truth follows a nearly-constant-velocity model ``x_k = F x_{k-1} + G w_k`` with
``w_k ~ N(0, σ_v² I)`` (eq. 21, 35). Each scan, each target is detected with probability ``p_D`` at
``H x + v``, ``v ~ N(0, σ_w² I)`` (eq. 22), and a classifier reports class ``ĉ`` with
``Pr{ĉ | c} = confusion[c, ĉ]`` (eq. 37). Clutter is Poisson with ``clutter_density`` points per
square metre, uniform over the surveillance rectangle, with classes drawn uniformly. Everything is
batched over Monte Carlo runs; measurements of a scan live in a fixed-capacity tensor with a mask and
are shuffled, so their order carries no information. Classes are 0-based (paper's class 1 is 0).
Tracks are started from a first measurement of each target (``first_z``, scan 0, always detected) and
the classifier reports of the ``init_reports`` detections that confirmed it (``first_class``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError


@dataclass
class FormationConfig:
    """Scenario constants (see ``configs/formation.yaml`` for the values used and why)."""

    num_steps: int = 60
    dt: float = 1.0
    speed: float = 25.0
    separation: float = 200.0
    classes: tuple[int, ...] = (0, 1, 0, 1)
    truth_sigma: float = 0.2           # m/s², truth acceleration noise σ_v
    measurement_sigma: float = 55.0    # m, σ_w
    p_detect: float = 0.96
    clutter_density: float = 1e-8      # points per m² (0.01 per km², the paper)
    margin: float = 500.0              # m, surveillance rectangle beyond the formation's extent
    confusion: list[list[float]] = field(default_factory=lambda: [[0.98, 0.02], [0.02, 0.98]])
    init_reports: int = 2              # classifier reports available when a track starts (confirmation)

    def region(self) -> tuple[float, float, float, float]:
        """Surveillance rectangle ``(x_min, x_max, y_min, y_max)`` in metres."""
        n = len(self.classes)
        length = self.speed * self.dt * self.num_steps
        return (-self.margin, length + self.margin, -self.margin, (n - 1) * self.separation + self.margin)


class FormationData(NamedTuple):
    truth: Tensor         # (R, K, N, 4) [x, y, vx, vy]
    z: Tensor             # (R, K, Mz, 2)
    z_class: Tensor       # (R, K, Mz) int64 classifier report
    z_origin: Tensor      # (R, K, Mz) int64 target index, -1 clutter, -2 empty slot
    z_mask: Tensor        # (R, K, Mz) bool
    target_class: Tensor  # (N,) int64
    first_z: Tensor       # (R, N, 2) the measurement each track starts from (scan 0, always detected)
    first_class: Tensor   # (R, N, init_reports) int64 classifier reports of the target before the track starts


def simulate_formation(cfg: FormationConfig, runs: int, generator: torch.Generator,
                       dtype: torch.dtype = torch.float64) -> FormationData:
    """Simulate ``runs`` independent realisations of the formation scenario."""
    if runs < 1:
        raise TorchtrackError(f"runs must be >= 1; got {runs}")
    conf = torch.as_tensor(cfg.confusion, dtype=dtype)
    C = conf.shape[0]
    cls = torch.as_tensor(cfg.classes, dtype=torch.long)
    if bool(((cls < 0) | (cls >= C)).any()):
        raise TorchtrackError(f"formation classes must lie in [0, {C}); got {list(cfg.classes)}")
    if not 0.0 < cfg.p_detect <= 1.0:
        raise TorchtrackError(f"p_detect must lie in (0, 1]; got {cfg.p_detect}")
    R, K, N, dt = runs, cfg.num_steps, len(cfg.classes), cfg.dt
    g = generator

    x0 = torch.zeros(N, 4, dtype=dtype)
    x0[:, 1] = torch.arange(N, dtype=dtype) * cfg.separation
    x0[:, 2] = cfg.speed
    w = torch.randn(R, K, N, 2, generator=g, dtype=dtype) * cfg.truth_sigma
    w[:, 0] = 0.0
    # x_k = F x_{k-1} + G w_k, unrolled: v_k = v_0 + dt Σ w, p_k = p_{k-1} + dt v_{k-1} + dt²/2 w_k
    v = x0[:, 2:] + dt * torch.cumsum(w, 1)
    v_prev = torch.cat([x0[:, 2:].expand(R, 1, N, 2), v[:, :-1]], 1)
    step = dt * v_prev + 0.5 * dt**2 * w
    step[:, 0] = 0.0
    p = x0[:, :2] + torch.cumsum(step, 1)
    truth = torch.cat([p, v], -1)

    detected = torch.rand(R, K, N, generator=g) < cfg.p_detect
    z_t = p + cfg.measurement_sigma * torch.randn(R, K, N, 2, generator=g, dtype=dtype)
    rep_t = torch.multinomial(conf[cls].repeat(R * K, 1), 1, generator=g).reshape(R, K, N)

    x_lo, x_hi, y_lo, y_hi = cfg.region()
    area = (x_hi - x_lo) * (y_hi - y_lo)
    counts = torch.poisson(torch.full((R, K), cfg.clutter_density * area, dtype=torch.float64), generator=g).long()
    cap = int(counts.max()) if counts.numel() else 0
    u = torch.rand(R, K, cap, 2, generator=g, dtype=dtype)
    z_c = torch.stack([x_lo + (x_hi - x_lo) * u[..., 0], y_lo + (y_hi - y_lo) * u[..., 1]], -1)
    rep_c = torch.randint(0, C, (R, K, cap), generator=g)
    live_c = torch.arange(cap) < counts.unsqueeze(-1)

    z = torch.cat([z_t, z_c], 2)
    rep = torch.cat([rep_t, rep_c], 2)
    origin = torch.cat([torch.arange(N).expand(R, K, N), torch.full((R, K, cap), -1)], 2)
    mask = torch.cat([detected, live_c], 2)
    origin = torch.where(mask, origin, torch.full_like(origin, -2))
    perm = torch.argsort(torch.rand(R, K, N + cap, generator=g), -1)
    z = torch.gather(z, 2, perm.unsqueeze(-1).expand(R, K, N + cap, 2))
    rep, origin, mask = (torch.gather(t, 2, perm) for t in (rep, origin, mask))
    z = torch.where(mask.unsqueeze(-1), z, torch.zeros_like(z))
    first_z = p[:, 0] + cfg.measurement_sigma * torch.randn(R, N, 2, generator=g, dtype=dtype)
    first_class = torch.multinomial(conf[cls].repeat(R, 1), cfg.init_reports, replacement=True,
                                    generator=g).reshape(R, N, cfg.init_reports)
    return FormationData(truth, z, rep, origin, mask, cls, first_z, first_class)


__all__ = ["FormationConfig", "FormationData", "simulate_formation"]
