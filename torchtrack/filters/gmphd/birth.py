"""Adaptive birth for the GM-PHD (Aguilar et al. 2023, section 2.4).

Measurement-driven birth (eq. 4): a measurement is a *birth measurement* when it lies farther than
``T_B`` from every predicted component (of weight at least ``suppress_weight``)::

    Z_k^b = { z ∈ Z_k : ‖H F x_i − z‖ > T_B  for all i }

Each birth measurement ``z_j = [p̄_j, v̄_j]`` spawns one component ``N(x; x_b(z_j), P_b)`` (eq. 5) of weight
``birth_weight`` with the initial state of eq. 6::

    x_b(z_j) = [p̄_j, h_v(p̄_j)]   where the velocity map has a value (‖h_v(p̄_j)‖ ≠ 0)
               [p̄_j, v̄_j]        otherwise, with the detector's velocity (the CNN's in the paper)
               [p̄_j, 0]          when neither is available (plain labelled GM-PHD)

with ``P_b`` diagonal: position ``σ_p²``, velocity ``σ_v²`` chosen by the velocity's source. Birth
components enter the mixture after the update of frame ``k`` and are first updated at frame ``k+1``
(Ristic, Clark, Vo & Vo 2012), so a single clutter point is never confirmed by itself.

The history-based velocity map ``h_v`` (Aguilar et al. 2022, the GLMB adaptive birth) is a grid over
the image: every confirmed estimate ``(p̂_i, v̂_i)`` with a settled velocity adds to its cell. A cell
answers ``h_v(p) = mean velocity`` when it holds at least ``min_count`` samples that agree (their
velocity spread at most ``max_spread``); cells on two-way roads or unvisited cells answer 0.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchtrack.association.grid import DENSE_PAIRS, disc_candidates
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.options import GMPHDBirthOptions, VelocityMapOptions
from torchtrack.gaussian import innovation_pairs, scalar, squared_norm
from torchtrack.params import Positive


class VelocityMap:
    """Grid of accumulated velocities (:class:`~torchtrack.filters.trackers.options.VelocityMapOptions`: ``cell``
    pixels per cell, ``shape = (rows, cols)`` cells starting at ``origin = (x0, y0)``, ``min_count``,
    ``max_spread``, ``decay``). Positions outside the grid are ignored (update) or answer nothing (lookup)."""

    def __init__(self, options: VelocityMapOptions | None = None, dtype: torch.dtype = torch.float32, device=None):
        self.options = options if options is not None else VelocityMapOptions()
        self.dtype, self.device = dtype, device
        self._geom: tuple[Tensor, Tensor, Tensor] | None = None   # origin, last cell, strides as tensors
        self.reset()

    def reset(self) -> None:
        n = self.options.shape[0] * self.options.shape[1]
        self.count = torch.zeros(n, dtype=self.dtype, device=self.device)
        self.sum_v = torch.zeros(n, 2, dtype=self.dtype, device=self.device)
        self.sum_v2 = torch.zeros(n, dtype=self.dtype, device=self.device)

    def _cells(self, pos: Tensor) -> tuple[Tensor, Tensor]:
        """Flat cell index ``(E,)`` (clamped into the grid) and a bool ``(E,)``: inside the grid."""
        o = self.options
        if self._geom is None or self._geom[0].dtype != pos.dtype or self._geom[0].device != pos.device:
            self._geom = (torch.tensor(o.origin, dtype=pos.dtype, device=pos.device),
                          torch.tensor([o.shape[1] - 1, o.shape[0] - 1], device=pos.device),  # last col, row
                          torch.tensor([1, o.shape[1]], device=pos.device))                 # flat strides
        origin, last, stride = self._geom
        colrow = torch.floor((pos - origin) / o.cell).long()                                  # (E, 2)
        clamped = torch.clamp(colrow, scalar(0, colrow), last)
        return (clamped * stride).sum(1), (clamped == colrow).all(1)      # inside: nothing was clamped

    def update(self, pos: Tensor, vel: Tensor) -> None:
        """Add estimates ``pos, vel (E, 2)`` to their cells (no gradient)."""
        decay = self.options.decay
        if decay < 1:
            self.count.mul_(decay)
            self.sum_v.mul_(decay)
            self.sum_v2.mul_(decay)
        if pos.shape[0] == 0:
            return
        pos, vel = pos.detach().to(self.dtype), vel.detach().to(self.dtype)
        cell, inside = self._cells(pos)
        w = inside.to(self.dtype)
        self.count.index_add_(0, cell, w)
        self.sum_v.index_add_(0, cell, vel * w.unsqueeze(1))
        self.sum_v2.index_add_(0, cell, vel.pow(2).sum(1) * w)

    def lookup(self, pos: Tensor) -> tuple[Tensor, Tensor]:
        """``h_v(p)`` for ``pos (B, 2)``: velocities ``(B, 2)`` and a bool ``(B,)`` where the map answers."""
        cell, inside = self._cells(pos.detach().to(self.dtype))
        c = self.count.index_select(0, cell)
        c_pos = c.clamp_min(1e-12)
        mean = self.sum_v.index_select(0, cell) / c_pos.unsqueeze(1)
        spread = self.sum_v2.index_select(0, cell) / c_pos - mean.pow(2).sum(1)
        valid = (inside & (c >= self.options.min_count) & (spread <= self.options.max_spread ** 2)
                 & (mean.norm(dim=1) > 0))
        return mean.to(pos.dtype), valid


def _detached(x: Tensor) -> Tensor:
    """``x`` without its gradient (itself where it has none: no operation while streaming)."""
    return x.detach() if x.requires_grad else x


class BirthConstants(NamedTuple):
    """The birth model's constrained parameters for one step: standard deviations and log-weight."""

    sigma_pos: Tensor
    sigma_vel_unknown: Tensor
    sigma_vel_detector: Tensor
    sigma_vel_map: Tensor
    log_weight: Tensor


class AdaptiveBirth(nn.Module):
    """Measurement-driven birth with velocity initialisation from a velocity map and/or the detector.

    ``options``: :class:`~torchtrack.filters.trackers.options.GMPHDBirthOptions` (meaning and defaults there); the
    birth weight and the position and velocity standard deviations are learnable parameters.
    """

    def __init__(self, options: GMPHDBirthOptions | None = None):
        super().__init__()
        o = self.options = options if options is not None else GMPHDBirthOptions()
        self.birth_weight = Positive(o.birth_weight, "birth_weight")
        self.sigma_pos = Positive(o.sigma_pos, "birth sigma_pos")
        self.sigma_vel_unknown = Positive(o.sigma_vel_unknown, "birth sigma_vel_unknown")
        self.sigma_vel_detector = Positive(o.sigma_vel_detector, "birth sigma_vel_detector")
        self.sigma_vel_map = Positive(o.sigma_vel_map, "birth sigma_vel_map")

    def new_velocity_map(self, dtype: torch.dtype, device=None) -> VelocityMap | None:
        return VelocityMap(self.options.velocity_map, dtype, device) if self.options.use_velocity_map else None

    def birth_measurements(self, pred_pos: Tensor, pred_log_w: Tensor, z: Tensor) -> Tensor:
        """Bool ``(M,)``: measurements farther than ``T_B`` from every predicted position (eq. 4).

        ``pred_pos (J, 2)`` predicted positions ``H F x_i``, ``pred_log_w (J,)`` their log-weights. The
        predictions within ``T_B`` of a measurement are found on a grid of the measurements
        (:func:`~torchtrack.association.grid.disc_candidates`, cells of side ``T_B``): memory and time follow the
        pairs that are near, not ``J M`` (up to :data:`~torchtrack.association.grid.DENSE_PAIRS` pairs, every
        distance at once).
        """
        if pred_pos.shape[0] == 0 or z.shape[0] == 0:
            return torch.ones(z.shape[0], dtype=torch.bool, device=z.device)
        # a selection: no gradient. A component below the suppression weight explains nothing (radius −1).
        reach = self.options.distance_threshold
        heavy = _detached(pred_log_w) > scalar(math.log(self.options.suppress_weight), pred_log_w)
        pos, z = _detached(pred_pos), _detached(z)
        if pos.shape[0] * z.shape[0] <= DENSE_PAIRS:
            d2 = squared_norm(innovation_pairs(pos, z))                                  # (M, J)
            return torch.where(heavy, d2, scalar(math.inf, d2)).amin(1) > scalar(reach**2, d2)
        radius = torch.where(heavy, scalar(reach, pos), scalar(-1.0, pos))
        jj, kk = disc_candidates(pos, radius, z, cell=reach)
        near = squared_norm(z.index_select(0, kk) - pos.index_select(0, jj)) <= scalar(reach**2, z)
        explained = torch.zeros(z.shape[0], dtype=torch.bool, device=z.device).index_fill_(0, kk[near], True)
        return ~explained

    def constants(self) -> BirthConstants:
        """The constrained parameters (compute once per step; differentiable)."""
        return BirthConstants(self.sigma_pos(), self.sigma_vel_unknown(), self.sigma_vel_detector(),
                              self.sigma_vel_map(), torch.log(self.birth_weight()))

    def forward(self, z: Tensor, velocity: Tensor | None, vmap: VelocityMap | None,
                consts: BirthConstants | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Birth components for birth measurements ``z (B, 2)`` (eq. 5–6).

        ``velocity (B, 2)`` the detector's velocities or None. Returns ``mean (B, 4)``, ``std (B, 4)``,
        ``log_weight (B,)`` (state layout ``[x, y, vx, vy]``).
        """
        if z.shape[1] != 2:
            raise TorchtrackError("AdaptiveBirth needs 2-D positions and a state [x, y, vx, vy]")
        c = consts if consts is not None else self.constants()
        B = z.shape[0]
        vel = torch.zeros(B, 2, dtype=z.dtype, device=z.device)
        s_vel = c.sigma_vel_unknown.expand(B)
        if velocity is not None and self.options.use_detector_velocity:
            vel = velocity
            s_vel = c.sigma_vel_detector.expand(B)
        if vmap is not None:
            hv, valid = vmap.lookup(z)
            vel = torch.where(valid.unsqueeze(1), hv, vel)
            s_vel = torch.where(valid, c.sigma_vel_map, s_vel)
        mean = torch.cat([z, vel], 1)
        std = torch.cat([c.sigma_pos.expand(B, 2), s_vel.unsqueeze(1).expand(B, 2)], 1)   # [σp, σp, σv, σv]
        return mean, std, c.log_weight.expand(B)
