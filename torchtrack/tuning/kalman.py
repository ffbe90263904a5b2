"""Tunable Kalman filter: process noise ``motion.q`` and measurement noise ``measurement.sigma``.

Items are single-target tracks ``Track(z (T, m), truth (T, m) | None)``; a batch is padded with NaN
rows (missing measurements) to ``(T, B, m)`` and filtered in one call.

Initialisation (the same for fitting and for evaluation): the first measurement ``z_0`` fixes the
prior ``x_0 ~ N([z_0, 0], blockdiag(R, σ_v² I, σ_a² I))`` — the exact posterior of the position
after ``z_0`` under a flat position prior, with a broad velocity (and acceleration) prior — and the
loss is the conditional marginal likelihood of the rest (Bar-Shalom et al. 2001, eq. 5.2.6-3)::

    log p(z_{1:T} | z_0) = Σ_k log N(ν_k; 0, S_k)

``nll`` returns its negative divided by the number of measurements; ``gospa`` the mean per frame of
the soft GOSPA^p (:func:`~torchtrack.tuning.losses.sinkhorn_gospa`) between the filtered position and
the truth (needs truth).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from torchtrack.errors import TorchtrackError
from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter
from torchtrack.models import ConstantAcceleration, ConstantVelocity, LinearPosition
from torchtrack.tuning.losses import sinkhorn_gospa
from torchtrack.tuning.registry import Tunable, TuneData, check_keys, split_items

OPTIONS = ("ndim", "motion", "noise", "q", "sigma", "dt", "init_velocity_std", "init_acceleration_std",
           "gospa_c", "gospa_p", "dtype")
DATA_KEYS = ("simulate", "file", "truth_file", "window", "held_out", "min_length", "shuffle")
SIM_KEYS = ("sequences", "steps", "q", "sigma", "speed", "area", "p_missing")


class Track(NamedTuple):
    """One single-target sequence: ``z (T, m)`` with NaN rows where missing; ``truth (T, m)`` or None."""

    z: Tensor
    truth: Tensor | None = None

    def cut(self, start: int, stop: int | None = None) -> Track:
        """Steps ``start:stop`` of the track."""
        return Track(self.z[start:stop], None if self.truth is None else self.truth[start:stop])


def _dtype(name: str) -> torch.dtype:
    if name not in ("float32", "float64"):
        raise TorchtrackError(f"model.dtype must be 'float32' or 'float64'; got {name!r}")
    return getattr(torch, name)


def psd_factor(Q: Tensor) -> Tensor:
    """A square root ``A`` with ``A Aᵀ = Q`` for a PSD (possibly singular) ``Q``."""
    evals, evecs = torch.linalg.eigh(Q)
    return evecs * evals.clamp_min(0).sqrt().unsqueeze(-2)


def pad_batch(items: Sequence[Track]) -> tuple[Tensor, Tensor | None]:
    """Stack tracks into ``(T, B, m)`` measurements (NaN-padded) and truth (or None if any lacks it)."""
    T = max(t.z.shape[0] for t in items)
    m = items[0].z.shape[-1]
    z = items[0].z.new_full((T, len(items), m), float("nan"))
    has_truth = all(t.truth is not None for t in items)
    truth = z.clone() if has_truth else None
    for b, t in enumerate(items):
        z[: t.z.shape[0], b] = t.z
        if truth is not None:
            truth[: t.truth.shape[0], b] = t.truth
    return z, truth


def windows(items: list[Track], length: int | None, min_length: int) -> list[Track]:
    """Cut tracks into consecutive windows of ``length`` steps (a shorter tail kept if ``>= min_length``);
    each window starts at a present measurement (leading missing rows are dropped)."""
    out = []
    for t in items:
        for piece in [t] if not length else [t.cut(s, s + length) for s in range(0, t.z.shape[0], length)]:
            present = ~torch.isnan(piece.z).any(-1)
            if int(present.sum()) >= max(min_length, 1):
                out.append(piece.cut(int(torch.nonzero(present)[0])))
    return out


def read_tracks(path: Path, dtype: torch.dtype, truth_path: Path | None = None) -> list[Track]:
    """One :class:`Track` per id of a MOTChallenge file (box centres; frames without the id are missing)."""
    from torchtrack.io.mot import read_mot

    data = read_mot(path)
    truth = read_mot(truth_path) if truth_path is not None else None
    tracks = []
    for ident in np.unique(data.id):
        frames = data.frame[data.id == ident]
        first, last = int(frames.min()), int(frames.max())
        tracks.append(Track(_centres(data, ident, first, last, dtype),
                            None if truth is None else _centres(truth, ident, first, last, dtype)))
    return tracks


def _centres(data, ident: int, first: int, last: int, dtype: torch.dtype) -> Tensor:
    """``(last − first + 1, 2)`` box centres of ``ident`` in frames ``first..last`` of ``data``, NaN where absent."""
    sel = (data.id == ident) & (data.frame >= first) & (data.frame <= last)
    out = torch.full((last - first + 1, 2), float("nan"), dtype=dtype)
    out[torch.as_tensor(data.frame[sel] - first)] = torch.as_tensor(data.centers()[sel], dtype=dtype)
    return out


class KalmanTunable(Tunable):
    """Kalman filter with a CV (or CA) motion model and a position measurement model."""

    name = "kalman"
    losses = ("nll", "gospa")
    option_keys, data_keys = OPTIONS, DATA_KEYS
    default_velocity_std, default_gospa_c = 100.0, 20.0

    def __init__(self, options: Mapping[str, Any] | None = None):
        super().__init__(options)
        check_keys(self.options, self.option_keys, f"model ({self.name})")
        self.ndim = self.number("ndim", 2, int)
        self.kind = self.options.get("motion", "cv")
        if self.kind not in ("cv", "ca"):
            raise TorchtrackError(f"model.motion must be 'cv' or 'ca'; got {self.kind!r}")
        self.dt = self.number("dt", 1.0)
        self.dtype = _dtype(self.options.get("dtype", "float64"))
        self.vel_std = self.number("init_velocity_std", self.default_velocity_std)
        self.acc_std = self.number("init_acceleration_std", 10.0)
        self.gospa_c = self.number("gospa_c", self.default_gospa_c)
        self.gospa_p = self.number("gospa_p", 2.0)

    def _motion(self, q: float) -> nn.Module:
        if self.kind == "cv":
            return ConstantVelocity(self.ndim, q, noise=self.options.get("noise", "cwna"))
        return ConstantAcceleration(self.ndim, q, noise=self.options.get("noise", "cwnj"))

    def _models(self) -> tuple[nn.Module, LinearPosition]:
        """The motion and measurement models at the start values ``q`` and ``sigma``."""
        motion = self._motion(self.number("q", 1.0))
        sigma = self.number("sigma", 1.0)
        return motion, LinearPosition(self.ndim, state_dim=motion.state_dim, sigma=sigma)

    def build(self) -> KalmanFilter:
        return KalmanFilter(*self._models()).to(self.dtype)

    # -- data -------------------------------------------------------------------------------------
    def simulate(self, cfg: Mapping[str, Any], generator: torch.Generator) -> list[Track]:
        """Tracks from the filter's own model with the true ``q`` and ``sigma`` of ``cfg``."""
        check_keys(cfg, SIM_KEYS, "data.simulate")
        B, T = int(cfg.get("sequences", 32)), int(cfg.get("steps", 100))
        if B < 1 or T < 2:
            raise TorchtrackError(f"data.simulate needs sequences >= 1 and steps >= 2; got {B}, {T}")
        motion = self._motion(float(cfg.get("q", 1.0))).to(self.dtype)
        sigma = float(cfg.get("sigma", 1.0))
        d, n = self.ndim, motion.state_dim
        with torch.no_grad():
            F = motion.transition_matrix(self.dt)
            A = psd_factor(motion.process_noise(self.dt))
            x = torch.zeros(B, n, dtype=self.dtype)
            x[:, :d] = torch.rand(B, d, generator=generator, dtype=self.dtype) * float(cfg.get("area", 1000.0))
            x[:, d: 2 * d] = torch.randn(B, d, generator=generator, dtype=self.dtype) * float(cfg.get("speed", 10.0))
            truth = []
            for _ in range(T):
                truth.append(x[:, :d])
                w = torch.randn(B, n, generator=generator, dtype=self.dtype)
                x = (F @ x.unsqueeze(-1)).squeeze(-1) + (A @ w.unsqueeze(-1)).squeeze(-1)
            pos = torch.stack(truth, 1)                                          # (B, T, d)
            z = pos + sigma * torch.randn(pos.shape, generator=generator, dtype=self.dtype)
            p_miss = float(cfg.get("p_missing", 0.0))
            if p_miss > 0:
                miss = torch.rand(B, T, generator=generator, dtype=self.dtype) < p_miss
                miss[:, 0] = False
                z[miss] = float("nan")
        return [Track(z[b], pos[b]) for b in range(B)]

    def tracks(self, config: Mapping[str, Any], generator: torch.Generator) -> list[Track]:
        """The tracks of the ``data`` section (simulated or read), before they are cut into windows."""
        if ("simulate" in config) == ("file" in config):
            raise TorchtrackError(f"data ({self.name}) needs exactly one of 'simulate' or 'file'")
        if "simulate" in config:
            items = self.simulate(config["simulate"] or {}, generator)
        else:
            truth = config.get("truth_file")
            items = read_tracks(Path(config["file"]), self.dtype, Path(truth) if truth else None)
        if config.get("shuffle", False):
            items = [items[i] for i in torch.randperm(len(items), generator=generator).tolist()]
        return items

    def load_data(self, config: Mapping[str, Any], generator: torch.Generator) -> TuneData:
        check_keys(config, self.data_keys, f"data ({self.name})")
        items = windows(self.tracks(config, generator), config.get("window"), int(config.get("min_length", 3)))
        if not items:
            raise TorchtrackError(f"data ({self.name}): no track with enough measurements (min_length "
                                  f"{int(config.get('min_length', 3))})")
        return split_items(items, config.get("held_out"), "data")

    def truth(self, data_config: Mapping[str, Any]) -> dict[str, Any]:
        sim = data_config.get("simulate")
        if not isinstance(sim, Mapping):
            return {}
        return {"motion.q": float(sim.get("q", 1.0)), "measurement.sigma": float(sim.get("sigma", 1.0))}

    # -- losses -----------------------------------------------------------------------------------
    def initial_state(self, module: KalmanFilter, z0: Tensor) -> GaussianState:
        """``N([z_0, 0], blockdiag(R, σ_v² I, σ_a² I))`` for ``z0 (B, m)``."""
        n, d = module.motion.state_dim, self.ndim
        mean = torch.cat([z0, z0.new_zeros(z0.shape[0], n - d)], -1)
        stds = [self.vel_std] + ([self.acc_std] if n > 2 * d else [])
        tail = torch.tensor([s**2 for s in stds for _ in range(d)], dtype=z0.dtype, device=z0.device)
        cov = torch.block_diag(module.measurement.noise_cov(), torch.diag(tail))
        return GaussianState(mean, cov.expand(z0.shape[0], n, n))

    def filter(self, module: KalmanFilter, items: Sequence[Track]):
        """Filter a batch: returns the :class:`FilterResult` (over steps ``1..T-1``), ``z`` and truth."""
        z, truth = pad_batch(items)
        z = z.to(self.dtype)
        result = module.run(z[1:], self.initial_state(module, z[0]), dt=self.dt, predict_first=True)
        return result, z, truth

    def loss(self, module: KalmanFilter, items: Sequence[Track], loss: str) -> Tensor:
        result, z, truth = self.filter(module, items)
        if loss == "nll":
            count = (~torch.isnan(z[1:]).any(-1)).sum().clamp_min(1)
            return -result.log_likelihood.sum() / count
        if truth is None:
            raise TorchtrackError("loss 'gospa' needs truth (simulated data, or data.truth_file)")
        est = result.mean[..., : self.ndim]                                      # (T-1, B, d)
        gt = truth[1:].to(est)
        present = ~torch.isnan(gt).any(-1)
        cost = sinkhorn_gospa(est.unsqueeze(-2), torch.nan_to_num(gt).unsqueeze(-2), truth_mask=present.unsqueeze(-1),
                              c=self.gospa_c, p=self.gospa_p)
        return cost.mean()

    def position_rmse(self, result, truth: Tensor | None) -> dict[str, float]:
        """``{"rmse": …}``: the position RMSE of a :meth:`filter` result against the truth (none without it)."""
        if truth is None:
            return {}
        err = (result.mean[..., : self.ndim] - truth[1:].to(result.mean)).pow(2).sum(-1)
        return {"rmse": float(err[~torch.isnan(err)].mean().sqrt())}

    def evaluate(self, module: KalmanFilter, items: Sequence[Track]) -> dict[str, float]:
        """Position RMSE against truth (where available) and the mean NIS per measurement dimension."""
        with torch.no_grad():
            result, z, truth = self.filter(module, items)
            present = ~torch.isnan(z[1:]).any(-1)
            return {"nis_per_dim": float(result.nis[present].mean() / self.ndim), **self.position_rmse(result, truth)}
