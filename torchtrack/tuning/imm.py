"""Tunable IMM (:class:`~torchtrack.filters.imm.cv.ConstantVelocityIMM`): the mode transition matrix
``transition.learned`` (a :class:`~torchtrack.params.RowStochastic`), the per-mode process noise
``motion.sigma (M,)`` and the measurement noise ``measurement.sigma``.

The models are the modes of a :class:`~torchtrack.models.ModeControlInput` — nearly constant velocity
with a mode-dependent acceleration ``u_j`` and noise ``σ_j`` (the gate paper's eq. 21–24) — and the
measurement is the position. Items are single-target tracks (:class:`~torchtrack.tuning.kalman.Track`)
as for the Kalman filter, initialised the same way (``x_0 ~ N([z_0, 0], blockdiag(R, σ_v² I))``, uniform
mode probabilities); the loss ``nll`` is the exact IMM marginal log-likelihood ``Σ_k log Σ_j c_j Λ_j``
(eq. 26–29) of the rest, per measurement; ``gospa`` as for the Kalman filter (the class extends
:class:`~torchtrack.tuning.kalman.KalmanTunable`, which holds the batching, initialisation and losses).

Simulated data (``data.simulate``) follow the IMM's own generative model on the formation scenario's
geometry (``sim.formation``): targets start on a vertical line ``separation`` apart moving along +x at
``speed``; each scan the mode follows the Markov chain ``p_ij`` and the target moves
``x_k = F x_{k-1} + G (u(m_k) + w_k)``, ``w_k ~ N(0, σ(m_k)² I)``; it is detected with ``p_detect`` at
``H x_k + v_k``, ``v_k ~ N(0, σ_w² I)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError
from torchtrack.filters.imm.cv import ConstantVelocityIMM
from torchtrack.filters.imm.filter import IMMState
from torchtrack.models import LinearPosition, ModeControlInput
from torchtrack.params import RowStochastic
from torchtrack.tuning.kalman import KalmanTunable, Track
from torchtrack.tuning.registry import check_keys

OPTIONS = ("controls", "sigma", "measurement_sigma", "transition", "transition_floor", "dt", "init_velocity_std",
           "gospa_c", "dtype")
DATA_KEYS = ("simulate", "window", "held_out", "min_length")
SIM_KEYS = ("runs", "targets", "steps", "speed", "separation", "controls", "sigma", "measurement_sigma",
            "transition", "p_detect")

DEFAULT_CONTROLS = [[0.0, 0.0], [0.0, 3 * 9.81], [0.0, -9.81]]   # the paper's class-1 set {0, 3g, −g}, lateral
DEFAULT_TRANSITION = [[0.95, 0.05, 0.0], [0.1, 0.8, 0.1], [0.0, 0.05, 0.95]]   # the paper's eq. 36


def floored_transition(value, floor: float) -> Tensor:
    """``value`` with entries at least ``floor`` and rows renormalised (RowStochastic needs p_ij > 0)."""
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.dim() != 2 or t.shape[0] != t.shape[1] or bool((t < 0).any()):
        raise TorchtrackError(f"transition must be a square non-negative matrix; got {t.tolist()}")
    t = t.clamp_min(floor)
    return t / t.sum(-1, keepdim=True)


class IMMTunable(KalmanTunable):
    """IMM with mode-control-input models (default: the gate paper's class-1 model set)."""

    name = "imm"
    option_keys, data_keys = OPTIONS, DATA_KEYS
    default_velocity_std, default_gospa_c = 50.0, 300.0

    def build(self) -> ConstantVelocityIMM:
        controls = self.options.get("controls", DEFAULT_CONTROLS)
        M = len(controls)
        motion = ModeControlInput(controls, self.options.get("sigma", 0.2))
        meas = LinearPosition(2, sigma=self.number("measurement_sigma", 100.0))
        T = floored_transition(self.options.get("transition", DEFAULT_TRANSITION),
                               self.number("transition_floor", 1e-3))
        if T.shape[0] != M:
            raise TorchtrackError(f"transition must be {M}x{M} for {M} modes; got {tuple(T.shape)}")
        return ConstantVelocityIMM(motion, meas, RowStochastic(T, "mode transition matrix")).to(self.dtype)

    # -- data -------------------------------------------------------------------------------------
    def simulate(self, cfg: Mapping[str, Any], generator: torch.Generator) -> list[Track]:
        check_keys(cfg, SIM_KEYS, "data.simulate")
        runs, N, K = int(cfg.get("runs", 8)), int(cfg.get("targets", 4)), int(cfg.get("steps", 60))
        if runs < 1 or N < 1 or K < 2:
            raise TorchtrackError(f"data.simulate needs runs, targets >= 1 and steps >= 2; got {runs}, {N}, {K}")
        dt = torch.float64
        motion = ModeControlInput(cfg.get("controls", DEFAULT_CONTROLS), cfg.get("sigma", 0.2)).double()
        P = torch.as_tensor(cfg.get("transition", DEFAULT_TRANSITION), dtype=dt)
        sw = float(cfg.get("measurement_sigma", 100.0))
        B = runs * N
        with torch.no_grad():
            F = motion.transition_matrix(self.dt)
            G = motion.gain(self.dt)
            x = torch.zeros(B, 4, dtype=dt)
            x[:, 1] = (torch.arange(B) % N).to(dt) * float(cfg.get("separation", 200.0))
            x[:, 2] = float(cfg.get("speed", 25.0))
            mode = torch.zeros(B, dtype=torch.long)
            sig = motion.sigma()
            truth = []
            for _ in range(K):
                truth.append(x[:, :2])
                mode = torch.multinomial(P[mode], 1, generator=generator).squeeze(-1)
                a = motion.controls[mode] + sig[mode, None] * torch.randn(B, 2, generator=generator, dtype=dt)
                x = x @ F.T + a @ G.T
            pos = torch.stack(truth, 1)                                        # (B, K, 2)
            z = pos + sw * torch.randn(pos.shape, generator=generator, dtype=dt)
            miss = torch.rand(B, K, generator=generator, dtype=dt) >= float(cfg.get("p_detect", 1.0))
            miss[:, 0] = False
            z[miss] = float("nan")
        return [Track(z[b].to(self.dtype), pos[b].to(self.dtype)) for b in range(B)]

    def tracks(self, config: Mapping[str, Any], generator: torch.Generator) -> list[Track]:
        if "simulate" not in config:
            raise TorchtrackError("data (imm) needs 'simulate' (the IMM's model on the formation geometry)")
        return self.simulate(config["simulate"] or {}, generator)

    def truth(self, data_config: Mapping[str, Any]) -> dict[str, Any]:
        sim = data_config.get("simulate")
        if not isinstance(sim, Mapping):
            return {}
        sigma = sim.get("sigma", 0.2)
        M = len(sim.get("controls", DEFAULT_CONTROLS))
        return {"transition.learned": torch.as_tensor(sim.get("transition", DEFAULT_TRANSITION)).tolist(),
                "motion.sigma": torch.as_tensor(sigma, dtype=torch.float64).expand(M).tolist(),
                "measurement.sigma": float(sim.get("measurement_sigma", 100.0))}

    # -- losses -----------------------------------------------------------------------------------
    def initial_state(self, module: ConstantVelocityIMM, z0: Tensor) -> IMMState:
        """Uniform mode probabilities, each mode at the Kalman tunable's ``N([z_0, 0], blockdiag(R, σ_v² I))``."""
        prior = super().initial_state(module, z0)
        return module.initial_state(prior.mean, prior.cov)

    def evaluate(self, module: ConstantVelocityIMM, items: Sequence[Track]) -> dict[str, float]:
        """Position RMSE of the combined estimate against the truth."""
        with torch.no_grad():
            result, _, truth = self.filter(module, items)
            return self.position_rmse(result, truth)
