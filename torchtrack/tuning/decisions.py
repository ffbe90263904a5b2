"""The trackers' options from a calibrated sensor (docs/calibrate.md, "Decisions"): the model's values by stated
rules, and the decisions that no closed form gives (the enhanced GM-PHD's birth weight and coasting) chosen by
the MOTA of a parametric bootstrap under the fitted model — no truth is used.

Rules:

- the filter's sensor and dynamics are the fitted ones (σ, p_D, κ, σ_v, q, p_S); the clutter's velocity density,
  a constant in the trackers, is the geometric mean of ``N(v; 0, τ² I)`` under itself, ``1 / (2π e τ²)``;
- births: position spread σ (the birth sits on a detection), velocity spread σ_v (from the detector's velocity);
- confirmation (GLMB ``confirm_frames``) by a sequential likelihood-ratio test: a new track is confirmed at the
  first ``n`` with ``n ℓ ≥ log B``, ``ℓ = log(p_D / κ) − log(2π σ²) − 1`` the expected log-ratio per frame of a
  target's detection against clutter, ``B`` anchored so that the benchmark sensor confirms where the built-in
  default does (:data:`CONFIRM_EVIDENCE`);
- PMB: clutter rate ``κ |A|`` over the detections' region, birth density from the fitted birth rate.

Bootstrap (:func:`bootstrap_decisions`): the last E-step's smoothed tracks are the pseudo-truth; detections are
simulated from them with the fitted p_D, σ, σ_v and clutter (velocities ``N(0, τ² I)``) over the last
:data:`BOOTSTRAP_FRAMES` frames; each candidate decision is scored by the tracker's MOTA on them, one option at a
time from the rules' configuration; the GLMB's clutter velocity density is chosen the same way with the GLMB
(rule or built-in), since it weighs false velocities in its own way.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchtrack.filters.trackers.options import POSITIONS_ONLY
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.io.mot import MOTData, from_points
from torchtrack.metrics.clear_mot import clear_mot
from torchtrack.sim.detections import simulate_detections
from torchtrack.tuning.calibrate import Calibration, Tracks

CONFIRM_EVIDENCE = math.log(1e4)
"""log B of the sequential test: the benchmark sensor (p_D 0.9, σ 1 px, κ 1e-4 px⁻²) has ℓ ≈ 6.3 per frame and
confirms at its second frame; the GLMB's built-in 3 frames are kept as a floor."""
BOOTSTRAP_FRAMES = 150
SEARCH: tuple[tuple[str, tuple], ...] = (
    ("birth_weight", (0.05, 0.02, 0.01, 0.005)),
    ("coast_threshold", (0.03, 0.1, None)),
    ("confirm_new", (True, 3)),
    ("velocity_clutter_density", (None, 2.5e-3)),
    ("extract_threshold", (0.5, 0.4, 0.65)),
)
"""The enhanced GM-PHD's decisions searched by the bootstrap, in order, each over these values (the first is
the built-in default; for the clutter's velocity density None is the rule's ``1 / (2π e τ²)`` and 2.5e-3 the
built-in uniform density over ±10 px/frame: the trackers hold one constant for every gate, and a gate around a
driving vehicle sees far fewer false velocities than the clutter's average)."""
MODEL_SEARCH: tuple[tuple[str, float], ...] = (
    ("sigma", 1.25),
    ("p_detection", 1.1),
    ("clutter_density", 2.0),
    ("q", 3.0),
    ("velocity_sigma", 1.25),
)
"""The fitted values the bootstrap then searches, each with its first step as a factor (p_D kept below 0.99): σ
with truth jitter and ``q`` of motion that is not constant velocity are not identified (docs/calibrate.md), so the
fit is where the search starts, not its answer."""
SEARCH_ROUNDS = 2
"""Rounds of the pattern search over :data:`MODEL_SEARCH`; each round takes the square root of the last one's
factors."""
MAX_MOVES = 3
"""Steps one value may take in one direction within a round."""


def confirm_frames(p_detection: float, sigma: float, clutter_density: float) -> int:
    """The smallest ``n`` with ``n ℓ ≥ log B`` (module docstring); 10 when a detection carries no evidence."""
    per_frame = math.log(p_detection / clutter_density) - math.log(2 * math.pi * sigma ** 2) - 1.0
    if per_frame <= 0:
        return 10
    return max(1, math.ceil(CONFIRM_EVIDENCE / per_frame))


def velocity_clutter_density(tau: float) -> float:
    """``1 / (2π e τ²)``: ``exp E[log N(v; 0, τ² I)]`` for ``v ~ N(0, τ² I)``."""
    return 1.0 / (2 * math.pi * math.e * tau ** 2)


def gmphd_section(values: dict[str, float], decisions: dict[str, Any] | None = None) -> dict[str, Any]:
    """The enhanced GM-PHD's options for fitted ``values`` (rules of the module docstring) with ``decisions``
    (the bootstrap's choices: ``birth_weight``, ``coast_threshold``, ``confirm_new``)."""
    filt = {"sigma": _r(values["sigma"]), "p_detection": _r(min(values["p_detection"], 0.99)),
            "clutter_density": _r(values["clutter_density"]), "q": _r(values["q"]),
            "p_survival": _r(min(max(values.get("p_survival", 0.99), 0.9), 0.999))}
    birth: dict[str, Any] = {"sigma_pos": _r(values["sigma"])}
    if "velocity_sigma" in values:
        filt["velocity_sigma"] = _r(values["velocity_sigma"])
        filt["velocity_clutter_density"] = _r(velocity_clutter_density(values["clutter_velocity_sigma"]))
        birth["sigma_vel_detector"] = _r(values["velocity_sigma"])
    out: dict[str, Any] = {"filter": filt, "birth": birth}
    if "velocity_sigma" not in values:       # the built-in positions-only options, but for the fitted sensor
        out["positions_only"] = {k: v for k, v in POSITIONS_ONLY.items() if k != "filter"}
    for key, value in (decisions or {}).items():
        if key == "birth_weight":
            birth[key] = value
        elif key == "glmb_velocity_clutter_density":
            continue
        elif key == "extract_threshold":
            filt[key] = value
        elif key == "velocity_clutter_density":
            if value is not None and "velocity_sigma" in values:
                filt[key] = value
        else:
            out[key] = value
    return out


def tracker_sections(cal: Calibration, decisions: dict[str, Any], searched: dict[str, float] | None = None
                     ) -> dict[str, Any]:
    """The ``track --config`` sections of gmphd, labelled-gmphd, glmb and pmb for a calibration; the GM-PHDs'
    from the bootstrap's ``searched`` values where given (the GLMB and PMB keep the fitted ones)."""
    v = cal.values
    fitted = gmphd_section(v, {key: value for key, value in decisions.items() if key != "extract_threshold"})
    labelled = {"filter": {k: x for k, x in fitted["filter"].items()
                           if k not in ("velocity_sigma", "velocity_clutter_density")},
                "birth": {"sigma_pos": fitted["birth"]["sigma_pos"],
                          "birth_weight": decisions.get("birth_weight", 0.05)}}
    pd, sigma, kappa = fitted["filter"]["p_detection"], v["sigma"], v["clutter_density"]
    glmb = {"sigma": _r(sigma), "p_detection": pd, "clutter_density": _r(kappa), "q": _r(v["q"]),
            "p_survival": fitted["filter"]["p_survival"], "birth_sigma_pos": _r(sigma),
            "confirm_frames": max(3, confirm_frames(pd, sigma, kappa))}
    if cal.velocities:
        glmb.update(velocity_sigma=_r(v["velocity_sigma"]), birth_sigma_vel_detector=_r(v["velocity_sigma"]),
                    velocity_clutter_density=decisions.get("glmb_velocity_clutter_density")
                    or fitted["filter"]["velocity_clutter_density"])
    x0, y0, x1, y1 = cal.region
    area = (x1 - x0) * (y1 - y0)
    pmb = {"sigma": _r(sigma), "p_detection": pd, "q": _r(v["q"]), "p_survival": fitted["filter"]["p_survival"],
           "clutter_rate": _r(kappa * area), "region": [x0, y0, x1, y1],
           "birth_density": _r(v["birth_rate"] / (area / 1e6))}
    gm = gmphd_section(searched or v, decisions)
    return {"gmphd": gm, "labelled-gmphd": labelled, "glmb": glmb, "pmb": pmb}


def _r(x: float) -> float:
    return float(f"{x:.4g}")


def pseudo_truth(tracks: Tracks, mean: torch.Tensor, first: int) -> MOTData:
    """The smoothed tracks as truth: every frame of each track's life (``mean (B, T, 4)``, window start
    ``first``)."""
    b, t = np.nonzero(np.arange(mean.shape[1])[None, :] < tracks.length[:, None])
    pos = mean[b, t, :2].numpy()
    frames = first + tracks.start[b] + t
    order = np.lexsort((b, frames))
    return from_points(frames[order], b[order] + 1, pos[order, 0], pos[order, 1])


@dataclass
class Bootstrap:
    """The bootstrap search's result: the enhanced GM-PHD's ``decisions`` and ``values`` (the fit moved by
    :data:`MODEL_SEARCH`), their MOTA on the simulated frames (``mota``), each tracker's MOTA there with its
    calibrated section and with its built-in options (``against_built_in``: name → (calibrated, built-in), for
    gmphd, glmb and pmb), every candidate's score (``log``) and the number of pseudo-truth points the MOTA is
    over (``points``: one error moves it by ``1 / points``)."""

    decisions: dict[str, Any]
    values: dict[str, float]
    mota: float
    against_built_in: dict[str, tuple[float, float]]
    log: list[dict]
    points: int


def bootstrap_decisions(cal: Calibration, truth: MOTData, seed: int = 0,
                        progress: Callable[[str], None] | None = None, base: dict | None = None) -> Bootstrap:
    """The enhanced GM-PHD's decisions (:data:`SEARCH`) and values (:data:`MODEL_SEARCH`) maximising MOTA on
    detections simulated under the fitted model from ``truth`` (the pseudo-truth) over its last
    :data:`BOOTSTRAP_FRAMES` frames: one coordinate pass over the decisions from the rules' configuration, then a
    pattern search over the values (each value stepped by its factor up, or else down, while the MOTA rises, at
    most :data:`MAX_MOVES` steps; :data:`SEARCH_ROUNDS` rounds of finer factors); a move is kept only where it
    scores higher. Each candidate's options go over ``base`` (:func:`merged`; default: none). The enhanced GM-PHD
    with ``base`` itself (its built-in options), and the GLMB and the PMB with their calibrated sections and their
    built-in options, are scored on the same frames."""
    v = cal.values
    last = int(truth.frame.max())
    truth = truth.select(truth.frame > last - BOOTSTRAP_FRAMES)
    x0, y0, x1, y1 = cal.region
    g = torch.Generator().manual_seed(seed)
    sim = simulate_detections(truth, pd=v["p_detection"], sigma=v["sigma"], clutter=v["clutter_density"] * x1 * y1,
                              image_size=(x1, y1), velocity_sigma=v.get("velocity_sigma"), generator=g)
    det = sim.detections
    if det.vx is not None:
        clutter = sim.source < 0
        tau = v["clutter_velocity_sigma"]
        noise = torch.randn(int(clutter.sum()), 2, generator=g, dtype=torch.float64).numpy() * tau
        det.vx[clutter], det.vy[clutter] = noise[:, 0], noise[:, 1]
    inputs = frame_inputs(det)

    def score(name: str, options: dict) -> float:
        options = merged(base or {}, options) if name == "gmphd" else options
        return float(clear_mot(truth, run_frames(make_tracker(name, options), inputs))["MOTA"])

    def say(line: str) -> None:
        if progress is not None:
            progress(line)

    chosen: dict[str, Any] = {key: values[0] for key, values in SEARCH}
    values = dict(v)
    best = score("gmphd", gmphd_section(values, chosen))
    log: list[dict] = [{"decisions": dict(chosen), "mota": best}]
    for key, options in SEARCH:
        if key == "velocity_clutter_density" and not cal.velocities:
            continue
        for option in options[1:]:
            trial = {**chosen, key: option}
            s = score("gmphd", gmphd_section(values, trial))
            log.append({"decisions": dict(trial), "mota": s})
            say(f"bootstrap {key}={option}: MOTA {s:.3f} (best {best:.3f})")
            if s > best:
                best, chosen = s, trial
    for rounds in range(SEARCH_ROUNDS):
        for key, step in MODEL_SEARCH:
            if key not in values:
                continue
            factor = step ** (0.5 ** rounds)
            for direction in (factor, 1 / factor):
                moved = False
                for _ in range(MAX_MOVES):
                    x = values[key] * direction
                    trial = {**values, key: min(x, 0.99) if key == "p_detection" else x}
                    if trial[key] == values[key]:
                        break
                    s = score("gmphd", gmphd_section(trial, chosen))
                    log.append({"values": {key: trial[key]}, "mota": s})
                    say(f"bootstrap {key}={trial[key]:.4g}: MOTA {s:.3f} (best {best:.3f})")
                    if s <= best:
                        break
                    best, values, moved = s, trial, True
                if moved:
                    break
    if cal.velocities:                       # the GLMB weighs false velocities in its own way: its own choice
        scores = {option: score("glmb", tracker_sections(cal, {**chosen, "glmb_velocity_clutter_density": option}
                                                         )["glmb"])
                  for option in dict(SEARCH)["velocity_clutter_density"]}
        log += [{"decisions": {"glmb_velocity_clutter_density": k}, "mota": x} for k, x in scores.items()]
        say(f"bootstrap glmb velocity_clutter_density: {scores}")
        chosen["glmb_velocity_clutter_density"] = max(scores, key=scores.get)
    sections = tracker_sections(cal, chosen, values)
    against = {"gmphd": (best, score("gmphd", {}))}
    for name in ("glmb", "pmb"):
        against[name] = (score(name, sections[name]), score(name, {}))
    for name, (mine, built_in) in against.items():
        log.append({"tracker": name, "calibrated": mine, "built-in": built_in})
        say(f"bootstrap {name}: MOTA {mine:.3f} calibrated, {built_in:.3f} built-in")
    return Bootstrap(chosen, values, best, against, log, truth.size)


def merged(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s keys set, mapping into mapping (``over`` wins)."""
    out = dict(base)
    for key, value in over.items():
        out[key] = merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def frame_inputs(det: MOTData) -> list[tuple[int, torch.Tensor, torch.Tensor | None]]:
    """``det`` as the trackers' ``step`` arguments, one per frame with detections."""
    if det.size == 0:
        return []
    frames = np.unique(det.frame)
    cx, cy = det.x + det.w / 2, det.y + det.h / 2
    bounds = np.searchsorted(det.frame, np.r_[frames, frames[-1] + 1])
    inputs = []
    for f, a, b in zip(frames, bounds[:-1], bounds[1:]):
        z = torch.from_numpy(np.stack([cx[a:b], cy[a:b]], 1))
        vel = None if det.vx is None else torch.from_numpy(np.stack([det.vx[a:b], det.vy[a:b]], 1))
        inputs.append((int(f), z, vel))
    return inputs


def run_frames(tracker, inputs: list[tuple[int, torch.Tensor, torch.Tensor | None]]) -> MOTData:
    """The tracks ``tracker`` reports over ``inputs`` (:func:`frame_inputs`)."""
    fr, ids, xs = [], [], []
    for f, z, vel in inputs:
        i, p = tracker.step(f, z, vel)
        fr += [f] * len(i)
        ids += i.tolist()
        xs.append(p.double().cpu().numpy().reshape(-1, 2))
    pts = np.concatenate(xs) if xs else np.zeros((0, 2))
    return from_points(fr, ids, pts[:, 0], pts[:, 1])
