"""SORT (Bewley, Ge, Ott, Ramos & Upcroft, "Simple online and realtime tracking", ICIP 2016) behind the interface
of :mod:`torchtrack.filters.trackers.protocol`: a constant-velocity Kalman filter per track, Hungarian assignment
on centre distance, birth/death rules (``min_hits``, ``max_age``)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor

from torchtrack.association.assignment import hungarian
from torchtrack.association.pairs import by_component, gated_pairs
from torchtrack.filters.trackers.options import SORTConfig, tracker_config
from torchtrack.filters.trackers.protocol import as_points, frame_step
from torchtrack.gaussian import kalman_update, symmetrize
from torchtrack.models import ConstantVelocity, LinearPosition


def sort(config: SORTConfig | Mapping | None = None) -> SORT:
    """SORT from its configuration (or the mapping of the keys to change)."""
    return SORT(tracker_config("sort", config))


DENSE_PAIRS = 1 << 20
"""SORT builds the dense track × detection distance matrix up to this many pairs; beyond, only the pairs within
``max_distance`` (k-d trees), assigned per connected component, so memory follows the gated pairs."""


def _hungarian_block(costs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`hungarian` on a dense block whose NaN entries are pairs outside the gate."""
    rows, cols = hungarian(np.nan_to_num(costs, nan=np.inf))
    return rows.numpy(), cols.numpy()


class SORT:
    """SORT (Bewley et al. 2016) on point detections.

    Each track is a constant-velocity Kalman filter ``[x, y, vx, vy]`` (all tracks batched); detections
    are assigned by the Hungarian algorithm on centre distance (pairs farther than ``max_distance`` are
    forbidden); an unmatched detection starts a track at rest (velocity std ``sigma_vel``); a track
    missed for more than ``max_age`` frames is deleted; a track is reported in a frame where it was
    updated once it has ``min_hits`` consecutive hits (or during the first ``min_hits`` frames). The options
    (:class:`~torchtrack.filters.trackers.options.SORTConfig`) are in px and frames.
    """

    def __init__(self, options: SORTConfig | None = None, dtype: torch.dtype = torch.float64):
        o = self.options = options if options is not None else SORTConfig()
        self.motion = ConstantVelocity(2, q=o.q, learnable=False).to(dtype)
        self.measurement = LinearPosition(2, sigma=o.sigma, learnable=False).to(dtype)
        self.dtype = dtype
        self.reset()

    def reset(self, device: torch.device | str = "cpu") -> None:
        """Forget all tracks; the next ones live on ``device`` (a stream starts on its first detections')."""
        self.device = torch.device(device)
        self.motion.to(self.device)
        with torch.no_grad():
            self.H, self.R = self.measurement.to(self.device).matrix(), self.measurement.noise_cov()
        self.mean = torch.empty(0, 4, dtype=self.dtype, device=self.device)
        self.cov = torch.empty(0, 4, 4, dtype=self.dtype, device=self.device)
        self.ids, self.streak, self.missed = (torch.empty(0, dtype=torch.long, device=self.device) for _ in range(3))
        self.next_id = 1
        self.frame_count = 0
        self._last_frame: int | None = None

    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None) -> tuple[Tensor, Tensor]:
        z = as_points(positions, self.dtype)
        if self._last_frame is None and z.device != self.device:
            self.reset(z.device)
        z = z.to(self.device)
        dt = frame_step(self._last_frame, frame)
        self._last_frame = frame
        self.frame_count += 1
        with torch.no_grad():
            F, Q = self.motion.transition_matrix(dt), self.motion.process_noise(dt)
            mean = self.mean @ F.T
            cov = symmetrize(F @ self.cov @ F.T + Q)
            T, M = mean.shape[0], z.shape[0]
            ti_t = di_t = torch.zeros(0, dtype=torch.long)   # the assignment is solved on the host (scipy)
            if T and M and T * M <= DENSE_PAIRS:
                dist = torch.cdist(mean[:, :2], z)
                ti_t, di_t = hungarian(dist, dist <= self.options.max_distance)
            elif T and M:          # many tracks and detections: only the gated pairs, solved per component
                i, j, d = gated_pairs(mean[:, :2].cpu().numpy(), z.cpu().numpy(), self.options.max_distance)
                ti, di, _ = by_component(T, M, i, j, d, _hungarian_block)
                order = np.argsort(ti)
                ti_t, di_t = torch.as_tensor(ti[order]), torch.as_tensor(di[order])
            ti_t, di_t = ti_t.to(self.device), di_t.to(self.device)
            if ti_t.numel():
                upd = kalman_update(mean[ti_t], cov[ti_t], z[di_t], self.H, self.R)
                mean[ti_t], cov[ti_t] = upd.mean, upd.cov
            hit = torch.zeros(T, dtype=torch.bool, device=self.device)
            hit[ti_t] = True
            streak = torch.where(hit, self.streak + 1, torch.zeros_like(self.streak))
            missed = torch.where(hit, torch.zeros_like(self.missed), self.missed + 1)
            new = torch.ones(M, dtype=torch.bool, device=self.device)
            new[di_t] = False
            zn = z[new]
            B = zn.shape[0]
            b_mean = torch.cat([zn, torch.zeros_like(zn)], 1)
            b_cov = torch.diag(torch.tensor([self.options.sigma**2] * 2 + [self.options.sigma_vel**2] * 2,
                                            dtype=self.dtype, device=self.device)).expand(B, 4, 4)
            keep = missed <= self.options.max_age
            self.mean = torch.cat([mean[keep], b_mean])
            self.cov = torch.cat([cov[keep], b_cov])
            self.ids = torch.cat([self.ids[keep], torch.arange(self.next_id, self.next_id + B, device=self.device)])
            self.streak = torch.cat([streak[keep], torch.ones(B, dtype=torch.long, device=self.device)])
            self.missed = torch.cat([missed[keep], torch.zeros(B, dtype=torch.long, device=self.device)])
            self.next_id += B
            hits = self.options.min_hits
            report = (self.missed == 0) & ((self.streak >= hits) | (self.frame_count <= hits))
            return self.ids[report], self.mean[report, :2].clone()
