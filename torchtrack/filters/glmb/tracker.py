"""The joint δ-GLMB (:mod:`torchtrack.filters.glmb.filter`) behind the streaming tracker interface of
:mod:`torchtrack.filters.trackers.protocol`.

``make_tracker("glmb", config)`` builds a :class:`GLMBTracker` (options and defaults:
:class:`~torchtrack.filters.trackers.options.GLMBConfig`). Per frame: the filter step with the births proposed
by the previous frame's measurements (:mod:`torchtrack.filters.glmb.birth`), the estimate (the heaviest
hypothesis of the MAP cardinality), and the **confirmation**: a label is reported from its ``confirm_frames``-th
consecutive frame in the estimate on, and afterwards whenever it is in the estimate. (The published GLMB reports
every birth at once, which floods the output with one-frame tracks from clutter.) Reported ids are the labels'
birth indices + 1. With the detector's velocities (and ``velocity_sigma``) the update uses ``[z, v]`` and births
start at the detector's velocity; without, positions only and births from pairs of consecutive measurements
(``birth_pairs`` > 0, (B3) of :mod:`~torchtrack.filters.glmb.birth`) or at rest (``birth_pairs: 0``, (B1)).
The filter runs on the host: detections on another device are copied there and the estimates returned on their
device.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.filters.glmb.birth import adaptive_births, no_births, scene_birth_rate, two_point_births
from torchtrack.filters.glmb.filter import GLMBFilter, GLMBState, empty_state
from torchtrack.filters.trackers.options import GLMBConfig, tracker_config
from torchtrack.models import ConstantVelocity, LinearPosition


def glmb(config: GLMBConfig | Mapping | None = None) -> GLMBTracker:
    """The GLMB tracker from its configuration (or the mapping of the keys to change from the defaults)."""
    return GLMBTracker(tracker_config("glmb", config))


class GLMBTracker:
    """Streaming joint δ-GLMB tracker (module docstring)."""

    def __init__(self, config: GLMBConfig):
        self.config = c = config
        self.dtype = {"float32": torch.float32, "float64": torch.float64}[c.dtype]
        with torch.no_grad():
            motion = ConstantVelocity(2, q=c.q, learnable=False).to(self.dtype)
            position = LinearPosition(2, sigma=c.sigma, learnable=False).to(self.dtype)
            self.F, self.Q = motion.transition_matrix(1.0), motion.process_noise(1.0)
            H_pos, R_pos = position.matrix(), position.noise_cov()
        H_full = R_full = None
        if c.velocity_sigma is not None:
            H_full = torch.eye(4, dtype=self.dtype)
            R_full = torch.diag(torch.tensor([c.sigma**2] * 2 + [c.velocity_sigma**2] * 2, dtype=self.dtype))
        self.generator = torch.Generator()
        self.filter = GLMBFilter(self.F, self.Q, H_pos, R_pos, H_full, R_full, c.p_survival, c.p_detection,
                                 c.gate, c.chains, c.sweeps, c.prune_threshold, c.max_hypotheses, self.generator)
        self.reset()

    @property
    def cap_hits(self) -> int:
        """Frames on which the hypothesis cap was hit."""
        return self.filter.cap_hits

    def reset(self) -> None:
        """Forget all tracks; the sampler's stream restarts from ``seed``."""
        self.generator.manual_seed(self.config.seed)
        self.filter.cap_hits = 0
        self.state: GLMBState = empty_state(4, self.dtype)
        self.births = no_births(self.dtype)
        self.previous = (torch.empty(0, 2, dtype=self.dtype), torch.empty(0, dtype=self.dtype))   # z, r_U
        self.next_index = 0
        self.streak_labels = torch.empty(0, dtype=torch.long)   # birth indices in the previous estimate
        self.streak = torch.empty(0, dtype=torch.long)          # their consecutive frames in the estimate
        self.confirmed = torch.empty(0, dtype=torch.long)
        self._last_frame: int | None = None

    @torch.no_grad()
    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """One frame: ``positions (M, 2)``, ``velocities (M, 2)`` or None → reported ``ids (E,)``, ``(E, 2)``."""
        c = self.config
        device = torch.as_tensor(positions).device
        if self._last_frame is not None and frame <= self._last_frame:
            raise TorchtrackError(f"glmb tracker: frames must increase: frame {frame} after {self._last_frame}")
        if self._last_frame is not None and frame != self._last_frame + 1:
            for skipped in range(self._last_frame + 1, frame):       # frames without detections
                self._advance(skipped, torch.empty(0, 2, dtype=self.dtype), None)
                if self._empty():   # a fixed point: the frames left in the gap change nothing (any gap, bounded)
                    break
        self._last_frame = frame
        z = torch.as_tensor(positions, dtype=self.dtype, device="cpu").reshape(-1, 2)
        v = None
        if velocities is not None and c.velocity_sigma is not None:
            v = torch.as_tensor(velocities, dtype=self.dtype, device="cpu").reshape(-1, 2)
        ids, estimates = self._advance(frame, z, v)
        return ids.to(device), estimates.to(device)

    def _empty(self) -> bool:
        """No table row, birth or estimate streak left: a frame without detections leaves the tracker as it is.
        Without detections every track's existence falls by ``p_S (1 - p_D)`` a frame until it is pruned, so a
        gap is crossed in a number of steps set by those probabilities, not by its length."""
        return not (self.state.mean.shape[0] or self.births.mean.shape[0] or len(self.streak))

    def _advance(self, frame: int, z: Tensor, v: Tensor | None) -> tuple[Tensor, Tensor]:
        c = self.config
        log_kappa = math.log(c.clutter_density) + (math.log(c.velocity_clutter_density) if v is not None else 0.0)
        log_clutter = torch.full((z.shape[0],), log_kappa, dtype=self.dtype)
        self.state, info = self.filter.step(self.state, self.births, z, log_clutter, v)
        rate = scene_birth_rate(z, c.birth_rate, c.birth_density)
        if v is None and c.birth_pairs > 0:
            self.births = two_point_births(z, info.used, *self.previous, frame, self.next_index, rate, c.birth_max,
                                           c.birth_min, c.birth_max_speed, c.birth_pairs, c.birth_sigma_pos,
                                           c.birth_sigma_vel_pair)
        else:
            self.births = adaptive_births(z, v, info.used, frame, self.next_index, rate, c.birth_max, c.birth_min,
                                          c.birth_sigma_pos, c.birth_sigma_vel, c.birth_sigma_vel_detector)
        self.previous = (z, info.used)
        self.next_index += self.births.mean.shape[0]
        rows = info.estimate
        labels = self.state.label[rows, 1]
        known = torch.isin(labels, self.streak_labels)
        before = self.streak[torch.searchsorted(self.streak_labels, labels).clamp_max(max(len(self.streak) - 1, 0))] \
            if len(self.streak) else torch.zeros_like(labels)
        streak = torch.where(known, before + 1, torch.ones_like(labels))
        order = labels.argsort()
        self.streak_labels, self.streak = labels[order], streak[order]
        report = (streak >= c.confirm_frames) | torch.isin(labels, self.confirmed)
        self.confirmed = torch.unique(torch.cat([self.confirmed, labels[report]]))
        return labels[report] + 1, self.state.mean[rows[report], :2].clone()
