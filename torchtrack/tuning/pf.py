"""Tunable bootstrap particle filter (:class:`~torchtrack.filters.particle.filter.ParticleFilter`) on the same
models, data and initialisation as the Kalman tunable (:mod:`torchtrack.tuning.kalman`).

The loss ``nll`` is minus the particle estimate of the conditional log-likelihood,
``−log p̂(z_{1:T} | z_0)`` per measurement. Resampling uses the stop-gradient correction of Ścibior &
Wood (2021), so the gradient of the estimate is an unbiased estimate of the score; each evaluation
draws its random numbers from a generator seeded with ``model.seed`` (common random numbers: the loss
is a deterministic, piecewise-smooth function of the parameters, which suits L-BFGS as well as Adam).
Missing measurements are not supported (the filter has no mask).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.filters.particle.filter import ParticleFilter
from torchtrack.tuning.kalman import OPTIONS, KalmanTunable, Track, pad_batch


class ParticleTunable(KalmanTunable):
    """Particle filter with a CV (or CA) motion model and a position measurement model."""

    name = "pf"
    losses = ("nll",)
    option_keys = (*OPTIONS, "particles", "resampler", "ess_threshold", "seed")

    def __init__(self, options: Mapping[str, Any] | None = None):
        super().__init__(options)
        self.seed = self.number("seed", 0, int)

    def build(self) -> ParticleFilter:
        ess = self.options.get("ess_threshold", 0.5)
        return ParticleFilter(*self._models(), self.number("particles", 500, int),
                              resampler=self.options.get("resampler", "systematic"),
                              ess_threshold=None if ess is None else float(ess)).to(self.dtype)

    def loss(self, module: ParticleFilter, items: Sequence[Track], loss: str) -> Tensor:
        z, _ = pad_batch(items)
        z = z.to(self.dtype)
        if bool(torch.isnan(z).any()):
            raise TorchtrackError("the particle filter tunable needs complete tracks of equal length (no NaN rows)")
        init = self.initial_state(module, z[0])
        gen = torch.Generator(device=z.device).manual_seed(self.seed)
        result = module.run(z[1:], init.mean, init.cov, self.dt, generator=gen)
        return -result.log_likelihood.sum() / (z.shape[0] - 1) / z.shape[1]

    def evaluate(self, module: ParticleFilter, items: Sequence[Track]) -> dict[str, float]:
        return {}
