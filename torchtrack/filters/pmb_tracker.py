"""The TOMB/P filter behind the streaming tracker interface of :mod:`torchtrack.filters.multitarget`.

``make_tracker("pmb", config)`` builds a :class:`PMBTracker` (options and their defaults:
:class:`~torchtrack.filters.tracker_config.PMBConfig`): point detections in pixels, a 2-D constant-velocity
:class:`~torchtrack.filters.pmb.PMBFilter`, and per frame the Bernoullis with existence above
``estimate_threshold`` reported with their labels (``id = label + 1``). Births come
from a broad Gaussian intensity covering ``region`` (centre, standard deviation of half its size);
clutter is ``clutter_rate`` false detections per frame spread uniformly over ``region``. Detector
velocities are not used.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb import PMBFilter, PMBState
from torchtrack.models import ConstantVelocity, LinearPosition


class PMBTracker:
    """Streaming TOMB/P tracker (module docstring)."""

    def __init__(self, q: float = 1.0, sigma: float = 2.0, p_survival: float = 0.99, p_detection: float = 0.9,
                 clutter_rate: float = 1.0, region: tuple[float, float, float, float] = (0.0, 0.0, 1024.0, 1024.0),
                 birth_weight: float = 0.1, sigma_vel: float = 5.0, capacity: int = 512,
                 estimate_threshold: float = 0.5, gate: float = 0.9999, lbp_iterations: int = 30):
        x0, y0, x1, y1 = (float(v) for v in region)
        if x1 <= x0 or y1 <= y0:
            raise TorchtrackError(f"pmb tracker: region must be [x0, y0, x1, y1] with x1 > x0, y1 > y0; got {region}")
        area = (x1 - x0) * (y1 - y0)
        birth_mean = torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2, 0.0, 0.0], dtype=torch.float64)
        birth_cov = torch.diag(torch.tensor([((x1 - x0) / 2) ** 2, ((y1 - y0) / 2) ** 2, sigma_vel**2, sigma_vel**2],
                                            dtype=torch.float64))
        self.filter = PMBFilter(
            ConstantVelocity(2, q=q, learnable=False), LinearPosition(2, sigma=sigma, learnable=False),
            p_survival=p_survival, p_detection=p_detection, clutter_intensity=clutter_rate / area,
            birth_weight=birth_weight, birth_mean=birth_mean, birth_cov=birth_cov, capacity=capacity,
            poisson_capacity=4, gate=gate, lbp_iterations=lbp_iterations, lbp_tol=1e-6,
            estimate_threshold=estimate_threshold, learnable=False).double()
        self.reset()

    def reset(self) -> None:
        self.state: PMBState = self.filter.init_state((), undetected_weight=0.0)
        self._last_frame: int | None = None

    @torch.no_grad()
    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None) -> tuple[Tensor, Tensor]:
        z = torch.as_tensor(positions, dtype=torch.float64).reshape(-1, 2)
        dt = 1.0 if self._last_frame is None else float(frame - self._last_frame)
        if dt <= 0:
            raise TorchtrackError(f"frames must increase: frame {frame} after {self._last_frame}")
        self._last_frame = frame
        self.state, _ = self.filter.step(self.state, z, dt=dt)
        est = self.filter.estimate(self.state)
        return est.label[est.mask] + 1, est.mean[est.mask][:, :2].clone()
