"""The test trajectory of the JTC particle-filter paper (Angelova, Mihaylova & Semerdjiev, section 4).

A target flying at 250 m/s performs coordinated turns with normal accelerations ``2g`` in scans
16–23 and ``−5g`` in scans 35–37, then ``1g`` longitudinal with ``2g`` normal acceleration in scans
45–47 (the speed rises to about 400 m/s), then turns of ``2g`` and ``−2g`` in scans 48–56 and 63–70.
Scan ``k`` is the measurement at time ``k T``; a maneuver "in scans a–b" acts on the motion from
time ``(k−1) T`` to ``k T`` for every ``a ≤ k ≤ b``. Positive normal acceleration turns left
(counter-clockwise). The paper's figure gives no coordinates; the start position and heading
here are documented defaults (``configs/jtc.yaml``) that keep the target 15–69 km from the radar.

The truth is integrated with the midpoint rule on ``substeps`` sub-intervals per scan
(``v̇ = a_t t̂ + a_n n̂``, ``t̂ = v/|v|``, ``n̂`` its left normal). State layout ``[x, y, vx, vy]``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.models.measurement import RangeBearing

G = 9.81
# (first scan, last scan, normal acceleration [g], longitudinal acceleration [g])
MANEUVERS = ((16, 23, 2.0, 0.0), (35, 37, -5.0, 0.0), (45, 47, 2.0, 1.0), (48, 56, 2.0, 0.0), (63, 70, -2.0, 0.0))


class Trajectory(NamedTuple):
    states: Tensor       # (K+1, 4) truth at times 0, T, …, K T
    acceleration: Tensor  # (K, 2) mean acceleration over each scan interval, Δv / T
    maneuvering: Tensor   # (K,) bool, a maneuver acts during scan k (index k−1)
    dt: float


def _accel(v: Tensor, a_n: float, a_t: float) -> Tensor:
    t = v / v.norm()
    n = torch.stack([-t[1], t[0]])
    return a_t * t + a_n * n


def jtc_trajectory(num_scans: int = 80, dt: float = 5.0, speed: float = 250.0,
                   start=(-10_000.0, 15_000.0), heading_deg: float = 0.0, substeps: int = 50,
                   maneuvers=MANEUVERS, dtype: torch.dtype = torch.float64) -> Trajectory:
    """Truth of the paper's scenario. ``heading_deg`` is the initial course counter-clockwise from +x."""
    h = math.radians(heading_deg)
    pos = torch.tensor(start, dtype=dtype)
    vel = torch.tensor([speed * math.cos(h), speed * math.sin(h)], dtype=dtype)
    states, accs, flags = [torch.cat([pos, vel])], [], []
    tau = dt / substeps
    for k in range(1, num_scans + 1):
        a_n = sum(m[2] for m in maneuvers if m[0] <= k <= m[1]) * G
        a_t = sum(m[3] for m in maneuvers if m[0] <= k <= m[1]) * G
        v0 = vel
        for _ in range(substeps):
            v_mid = vel + 0.5 * tau * _accel(vel, a_n, a_t)
            a = _accel(v_mid, a_n, a_t)
            pos = pos + tau * vel + 0.5 * tau**2 * a
            vel = vel + tau * a
        states.append(torch.cat([pos, vel]))
        accs.append((vel - v0) / dt)
        flags.append(a_n != 0.0 or a_t != 0.0)
    return Trajectory(torch.stack(states), torch.stack(accs), torch.tensor(flags), dt)


def true_modes(traj: Trajectory) -> Tensor:
    """The filter mode closest to the truth per scan ``(K,)``, 0-based: 0 (no acceleration) while not
    maneuvering, else the mode ``(±A, ±A)`` whose signs match the mean acceleration:
    1 ``(+,+)``, 2 ``(+,−)``, 3 ``(−,+)``, 4 ``(−,−)`` (the paper's modes 1–5)."""
    a = traj.acceleration
    quadrant = 1 + 2 * (a[:, 0] < 0).long() + (a[:, 1] < 0).long()
    return torch.where(traj.maneuvering, quadrant, torch.zeros_like(quadrant))


def simulate_measurements(traj: Trajectory, sensor: RangeBearing, runs: int,
                          generator: torch.Generator | None = None) -> Tensor:
    """Range–bearing measurements ``(K, runs, 2)`` of scans 1…K with independent noise per run."""
    x = traj.states[1:]
    z = sensor.measure(x).detach().unsqueeze(1)
    std = torch.stack([sensor.sigma_range(), sensor.sigma_bearing()]).detach().to(x)
    noise = torch.randn((x.shape[0], runs, 2), generator=generator, dtype=x.dtype) * std
    return z + noise
