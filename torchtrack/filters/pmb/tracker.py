"""The TOMB/P filter behind the streaming tracker interface of :mod:`torchtrack.filters.trackers.protocol`.

``make_tracker("pmb", config)`` builds a :class:`PMBTracker` (options and their defaults:
:class:`~torchtrack.filters.trackers.options.PMBConfig`): point detections in pixels, a 2-D constant-velocity
:class:`~torchtrack.filters.pmb.filter.PMBFilter`, and per frame the Bernoullis with existence above
``estimate_threshold`` reported with their labels (``id = label + 1``). Births come
from a broad Gaussian intensity covering ``region`` (centre, standard deviation of half its size) with
:func:`birth_weight` expected births per frame, which follows the region's area as the clutter does;
clutter is ``clutter_rate`` false detections per frame spread uniformly over ``region``. The association runs
on the gated pairs only (``sparse``) and the Bernoulli slots follow the scene (``capacity`` their floor,
``capacity_limit`` an optional hard limit). Detector velocities are not used.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from torchtrack.filters.pmb.filter import PMBFilter, PMBState
from torchtrack.filters.trackers.options import PMBConfig, tracker_config
from torchtrack.filters.trackers.protocol import frame_step
from torchtrack.models import ConstantVelocity, LinearPosition


def birth_weight(config: PMBConfig) -> float:
    """Expected births per frame over the region: ``max(birth_weight, birth_density · area [Mpx])``."""
    x0, y0, x1, y1 = config.region
    return max(config.birth_weight, config.birth_density * (x1 - x0) * (y1 - y0) / 1e6)


class PMBTracker:
    """Streaming TOMB/P tracker (module docstring) from its configuration (or the mapping of the keys to change;
    None: the defaults)."""

    def __init__(self, config: PMBConfig | Mapping | None = None):
        c = tracker_config("pmb", config)
        x0, y0, x1, y1 = c.region
        area = (x1 - x0) * (y1 - y0)
        birth_mean = torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2, 0.0, 0.0], dtype=torch.float64)
        birth_cov = torch.diag(torch.tensor([((x1 - x0) / 2) ** 2, ((y1 - y0) / 2) ** 2, c.sigma_vel**2,
                                             c.sigma_vel**2], dtype=torch.float64))
        self.filter = PMBFilter(
            ConstantVelocity(2, q=c.q, learnable=False), LinearPosition(2, sigma=c.sigma, learnable=False),
            p_survival=c.p_survival, p_detection=c.p_detection, clutter_intensity=c.clutter_rate / area,
            birth_weight=birth_weight(c), birth_mean=birth_mean, birth_cov=birth_cov, capacity=c.capacity,
            poisson_capacity=4, gate=c.gate, lbp_iterations=c.lbp_iterations, lbp_tol=1e-6,
            estimate_threshold=c.estimate_threshold, learnable=False, capacity_limit=c.capacity_limit,
            sparse=True).double()
        self.reset()

    def reset(self) -> None:
        self.state: PMBState = self.filter.init_state((), undetected_weight=0.0, device=self.device)
        self._last_frame: int | None = None

    @property
    def device(self) -> torch.device:
        """Where the filter and its state live: a stream starts on the device of its first frame's detections."""
        return self.filter.birth_mean.device

    @torch.no_grad()
    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None) -> tuple[Tensor, Tensor]:
        positions = torch.as_tensor(positions)
        if self._last_frame is None and positions.device != self.device:
            self.filter.to(positions.device)
            self.reset()
        z = torch.as_tensor(positions, dtype=torch.float64, device=self.device).reshape(-1, 2)
        dt = frame_step(self._last_frame, frame)
        self._last_frame = frame
        self.state, _ = self.filter.step(self.state, z, dt=dt)
        est = self.filter.estimate(self.state)
        return est.label[est.mask] + 1, est.mean[est.mask][:, :2].clone()
