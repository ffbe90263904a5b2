"""Truth and measurements for the maneuver paper's three experiments, batched over runs.

All functions return tensors with time first: truth ``(T, R, n)``, measurements ``(T, R, m)``.
Units: the stationary experiment is in arc-seconds of latitude/longitude (the localiser output
10°04'00'' N, 76°21'00'' E with unit noise, §4); the moving experiments in metres.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError

STATIONARY_LAT_LON_ARCSEC = (10 * 3600 + 4 * 60.0, 76 * 3600 + 21 * 60.0)


class Sequence(NamedTuple):
    truth: Tensor         # (T, R, n) true states
    measurements: Tensor  # (T, R, m)


def _noise(shape, sigma: float, generator: torch.Generator, dtype) -> Tensor:
    return sigma * torch.randn(shape, generator=generator, dtype=dtype)


def stationary(scans: int, runs: int, sigma: float, generator: torch.Generator,
               dtype=torch.float64) -> Sequence:
    """A stationary target at the paper's latitude/longitude, measured with noise ``sigma`` (§3.1)."""
    truth = torch.tensor(STATIONARY_LAT_LON_ARCSEC, dtype=dtype).expand(scans, runs, 2)
    return Sequence(truth, truth + _noise((scans, runs, 2), sigma, generator, dtype))


def turn_rates(scans: int, onsets: list[int], turn_deg: list[float], duration: int, dt: float) -> Tensor:
    """Per-scan turn rate (rad/s): maneuver ``i`` turns by ``turn_deg[i]`` over ``duration`` scans
    starting so that the position at scan ``onsets[i]`` (1-based) is the first one off the straight line.
    An onset outside scans ``1..scans`` (a maneuver that never happens), a ``turn_deg`` per onset missing, or
    ``duration < 1`` is an error."""
    if len(turn_deg) != len(onsets):
        raise TorchtrackError(f"maneuver: turn_deg needs one angle per onset ({len(onsets)}); got {len(turn_deg)}")
    if duration < 1:
        raise TorchtrackError(f"maneuver: turn_scans must be >= 1; got {duration}")
    for i, onset in enumerate(onsets):
        if not 1 <= onset <= scans:
            raise TorchtrackError(f"maneuver: onsets[{i}] must be a scan in [1, {scans}] (scans); got {onset}")
    omega = torch.zeros(scans, dtype=torch.float64)
    for onset, deg in zip(onsets, turn_deg):
        omega[onset - 1: onset - 1 + duration] = math.radians(deg) / (duration * dt)
    return omega


def maneuvering(scans: int, runs: int, speed: float, onsets: list[int], turn_deg: list[float],
                turn_scans: int, sigma: float, sigma_a: float, dt: float, generator: torch.Generator,
                dtype=torch.float64) -> Sequence:
    """A nearly-constant-velocity target (white acceleration ``sigma_a``) that executes coordinated
    turns of ``turn_deg`` degrees over ``turn_scans`` scans at the given 1-based onset scans.

    With no onsets it is the constant-velocity experiment of §3.2. State ``[x, y, vx, vy]``.
    """
    omega = turn_rates(scans, onsets, turn_deg, turn_scans, dt)
    pos = torch.zeros(runs, 2, dtype=dtype)
    vel = torch.tensor([speed, 0.0], dtype=dtype).expand(runs, 2).clone()
    acc_noise = _noise((scans, runs, 2), sigma_a, generator, dtype)
    states = []
    for k in range(scans):
        if k > 0:
            w = float(omega[k - 1])
            c, s = math.cos(w * dt), math.sin(w * dt)
            a = acc_noise[k]
            new_vel = torch.stack([c * vel[:, 0] - s * vel[:, 1], s * vel[:, 0] + c * vel[:, 1]], -1)
            pos = pos + 0.5 * (vel + new_vel) * dt + 0.5 * a * dt**2
            vel = new_vel + a * dt
        states.append(torch.cat([pos, vel], -1))
    truth = torch.stack(states)
    return Sequence(truth, truth[..., :2] + _noise((scans, runs, 2), sigma, generator, dtype))
