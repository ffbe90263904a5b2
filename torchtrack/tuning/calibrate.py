"""Calibration of a tracker to a new sensor from its detections alone (``torchtrack calibrate``;
docs/calibrate.md).

Expectation–maximisation with the tracker as the E-step:

1. **E-step** — the enhanced GM-PHD, configured from the current estimate (:mod:`torchtrack.tuning.decisions`),
   tracks the training frames; each confirmed track takes the nearest detection within ``3 σ`` of its estimate
   at each frame it is reported; tracks with fewer than :data:`MIN_DETECTIONS` detections are dropped; a
   batched CV Rauch–Tung–Striebel smoother (:mod:`torchtrack.tuning.track_smoother`) gives every frame of a
   track's life (first to last detection) the leave-one-out predictive of its detection.
2. **M-step** — the clutter density κ and velocity spread τ are measured in the cells no track crosses
   (:mod:`torchtrack.tuning.background`); σ, p_D and (with velocities) σ_v maximise the multi-object
   likelihood of every frame's detections given the smoothed states (:mod:`torchtrack.tuning.sensor_likelihood`),
   from three starts of p_D (the share of the frames inside the tracks' lives with a detection, 0.5 and 0.9;
   the best is kept); each track's CWNA ``q`` maximises its Kalman likelihood on :data:`Q_GRID` and the tracker's
   is their median; survival and birth rate are counted from the tracks' ends and starts.

The iteration starts from :func:`initial_values` and runs :data:`ITERATIONS` times (one: a second E-step
with the fitted sensor but the built-in decisions drifted on the harshest validation sensor).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.io.mot import MOTData
from torchtrack.tuning.background import measure_background
from torchtrack.tuning.sensor_likelihood import SensorPairs, fit_sensor_likelihood, other_tracks, to_theta
from torchtrack.tuning.track_smoother import q_profile, smooth

ITERATIONS = 1
MIN_DETECTIONS = 5
"""A confirmed track enters the M-step with at least this many detections (shorter ones are mostly clutter)."""
CANDIDATES = 6
"""Detections nearest a track's predictive mean that enter its factor of the likelihood."""
EDGE_FRAMES = 5
"""Tracks ending (starting) this close to the window's last (first) frame do not count as deaths (births)."""


@dataclass(frozen=True)
class DetectionFrames:
    """The detections of the calibration window, one entry per frame from ``first`` to ``last`` (empty frames
    included): ``positions[k] (K, 2)`` centres, ``velocities[k] (K, 2)`` or None; ``region`` their bounding box
    ``(x0, y0, x1, y1)``."""

    first: int
    last: int
    positions: list[np.ndarray]
    velocities: list[np.ndarray] | None
    region: tuple[float, float, float, float]

    @property
    def count(self) -> int:
        return int(sum(len(p) for p in self.positions))

    @property
    def area(self) -> float:
        x0, y0, x1, y1 = self.region
        return (x1 - x0) * (y1 - y0)

    def frame_input(self, k: int) -> tuple[int, torch.Tensor, torch.Tensor | None]:
        v = None if self.velocities is None else torch.from_numpy(self.velocities[k])
        return self.first + k, torch.from_numpy(self.positions[k]), v


def detection_frames(det: MOTData, frames: tuple[int, int] | None = None, velocity: bool | None = None,
                     source: str = "detections") -> DetectionFrames:
    """The window ``frames = (A, B)`` (inclusive; None: all) of ``det``; ``velocity`` True asks for the velocity
    fit (an error without velocities), False ignores them, None uses them where present."""
    if det.size == 0:
        raise TorchtrackError(f"{source}: no detections")
    keep = np.ones(det.size, bool) if frames is None else (det.frame >= frames[0]) & (det.frame <= frames[1])
    if not keep.any():
        raise TorchtrackError(f"{source}: no detections in frames {frames[0]}-{frames[1]}")
    frame = det.frame[keep]
    first, last = int(frame.min()), int(frame.max())
    if first == last:
        raise TorchtrackError(f"{source}: detections in 1 frame only ({first}); calibration needs several")
    has_v = det.vx is not None and bool(np.isfinite(det.vx[keep]).all())
    if velocity and not has_v:
        raise TorchtrackError(f"{source}: no velocities (columns 8-9) to fit the velocity noise on")
    use_v = has_v if velocity is None else velocity
    cx, cy = det.x[keep] + det.w[keep] / 2, det.y[keep] + det.h[keep] / 2
    pts = np.stack([cx, cy], 1)
    vel = np.stack([det.vx[keep], det.vy[keep]], 1) if use_v else None
    order = np.argsort(frame, kind="stable")
    frame, pts = frame[order], pts[order]
    vel = vel[order] if vel is not None else None
    bounds = np.searchsorted(frame, np.arange(first, last + 2))
    positions = [pts[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
    velocities = None if vel is None else [vel[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
    region = (float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max()))
    return DetectionFrames(first, last, positions, velocities, region)


class NoTracks(TorchtrackError):
    """The E-step confirmed no track long enough to fit the sensor on."""


@dataclass
class Tracks:
    """Confirmed tracks of an E-step: ``z (B, T, m)`` each track's detections from its first (NaN: none),
    ``start (B,)`` the window index of its first detection, ``length (B,)`` frames to its last one,
    ``detected (B, T)`` whether a detection was taken."""

    z: torch.Tensor
    start: np.ndarray
    length: np.ndarray
    detected: torch.Tensor


def run_tracker(data: DetectionFrames, config: dict, bar: str | None = None
                ) -> dict[int, list[tuple[int, np.ndarray]]]:
    """Confirmed tracks of the enhanced GM-PHD with ``config`` over the window: id → [(window index, position)];
    ``bar``: draw a progress bar with this label (on stderr)."""
    tracker = make_tracker("gmphd", config)
    out: dict[int, list[tuple[int, np.ndarray]]] = {}
    for k in tqdm(range(len(data.positions)), desc=bar, disable=bar is None, leave=False, unit="frame"):
        ids, pos = tracker.step(*data.frame_input(k))
        for i, p in zip(ids.tolist(), pos.cpu().double().numpy()):
            out.setdefault(i, []).append((k, p))
    return out


def associate(data: DetectionFrames, tracks: dict[int, list[tuple[int, np.ndarray]]], radius: float) -> Tracks:
    """Each track's nearest detection within ``radius`` px at each frame it is reported."""
    trees = [cKDTree(p) if len(p) else None for p in data.positions]
    rows = []
    for points in tracks.values():
        taken = []
        for k, p in points:
            if trees[k] is None:
                continue
            d, j = trees[k].query(p, distance_upper_bound=radius)
            if np.isfinite(d):
                z = data.positions[k][j]
                taken.append((k, z if data.velocities is None else np.concatenate([z, data.velocities[k][j]])))
        if len(taken) >= MIN_DETECTIONS:
            rows.append(taken)
    m = 2 if data.velocities is None else 4
    if not rows:
        return Tracks(torch.zeros(0, 1, m, dtype=torch.float64), np.zeros(0, int), np.zeros(0, int),
                      torch.zeros(0, 1, dtype=torch.bool))
    start = np.array([r[0][0] for r in rows])
    length = np.array([r[-1][0] - r[0][0] + 1 for r in rows])
    z = np.full((len(rows), int(length.max()), m), np.nan)
    for b, r in enumerate(rows):
        for k, value in r:
            z[b, k - start[b]] = value
    zt = torch.from_numpy(z)
    return Tracks(zt, start, length, ~torch.isnan(zt).any(-1))


def sensor_pairs(data: DetectionFrames, tracks: Tracks, loo_mean: torch.Tensor, loo_cov: torch.Tensor,
                 radius: float, clutter_density: float, clutter_velocity_sigma: float | None) -> SensorPairs:
    """The likelihood's data: every frame of every track's life with its :data:`CANDIDATES` nearest detections
    within ``radius`` px, and the log-intensity of what is not the track at each: the clutter's, or the local
    density of detections in the ring from ``radius`` to ``2 radius`` around the track over its life where that
    is higher (vehicles parked beside the track that no track follows: on WPAFB truth 29 % of the vehicles have
    another within 6 px)."""
    B, T = tracks.detected.shape
    length = torch.from_numpy(tracks.length)
    alive = torch.arange(T)[None, :] < length[:, None]
    bi, ti = torch.nonzero(alive, as_tuple=True)
    endpoint = (ti == 0) | (ti == length[bi] - 1)
    frame_np = (torch.from_numpy(tracks.start)[bi] + ti).numpy()
    mu_np = loo_mean[bi, ti].numpy()
    tf, res, log_c, det, ring_tf, ring_n = [], [], [], [], [], []
    offsets = np.cumsum([0] + [len(p) for p in data.positions])
    order = np.argsort(frame_np, kind="stable")
    bounds = np.searchsorted(frame_np[order], np.arange(len(data.positions) + 1))
    for k in range(len(data.positions)):
        idx = order[bounds[k]:bounds[k + 1]]
        pts = data.positions[k]
        if not len(idx) or not len(pts):
            continue
        tree = cKDTree(pts)
        ring_tf.append(idx)
        ring_n.append(tree.query_ball_point(mu_np[idx, :2], 2 * radius, return_length=True)
                      - tree.query_ball_point(mu_np[idx, :2], radius, return_length=True))
        d, j = tree.query(mu_np[idx, :2], k=min(CANDIDATES, len(pts)), distance_upper_bound=radius)
        d, j = d.reshape(len(idx), -1), j.reshape(len(idx), -1)
        rows, cols = np.nonzero(np.isfinite(d))
        jj = j[rows, cols]
        lc = np.zeros(len(jj))
        if data.velocities is None:
            z = pts[jj]
        else:
            v = data.velocities[k][jj]
            z = np.concatenate([pts[jj], v], 1)
            t2 = clutter_velocity_sigma ** 2
            lc -= 0.5 * np.sum(v ** 2, 1) / t2 + math.log(2 * math.pi * t2)
        tf.append(idx[rows])
        res.append(z - mu_np[idx[rows]])
        log_c.append(lc)
        det.append(offsets[k] + jj)
    per_frame = np.zeros(len(bi))
    per_frame[np.concatenate(ring_tf)] = np.concatenate(ring_n)
    bi_np = bi.numpy()
    local = np.bincount(bi_np, per_frame, B) / np.maximum(np.bincount(bi_np, None, B), 1) / (3 * math.pi * radius ** 2)
    density = np.maximum(local, clutter_density)[bi_np[np.concatenate(tf)]]
    return SensorPairs(log_clutter=torch.from_numpy(np.concatenate(log_c) + np.log(density)), endpoint=endpoint,
                       loo_cov=loo_cov[bi, ti], track_frame=torch.from_numpy(np.concatenate(tf)),
                       detection=torch.from_numpy(np.unique(np.concatenate(det), return_inverse=True)[1]),
                       residual=torch.from_numpy(np.concatenate(res)))


Q_GRID = torch.logspace(-3, math.log10(50.0), 15, dtype=torch.float64)
"""Process noises (px²/frame³) among which each track's and the tracker's ``q`` are chosen."""


def fit_q(tracks: Tracks, sigma: float, velocity_sigma: float | None) -> tuple[float, torch.Tensor]:
    """Each track's CWNA spectral density (its Kalman likelihood's maximiser on :data:`Q_GRID`, so that parked
    and driving vehicles each get theirs) and the tracker's: their median weighted by the tracks' detections
    (robust to the few tracks whose wrong detections call for a huge ``q``)."""
    ll = q_profile(tracks.z, Q_GRID, sigma, velocity_sigma)
    per_track = Q_GRID[ll.argmax(0)]
    weight = tracks.detected.sum(1).double()
    order = torch.argsort(per_track)
    cum = torch.cumsum(weight[order], 0)
    median = per_track[order][int(torch.searchsorted(cum, 0.5 * cum[-1]))]
    return float(median), per_track


def life_rates(tracks: Tracks, frames: int) -> tuple[float, float]:
    """Survival probability per frame (1 − deaths / frames lived) and births per frame, counting only the
    tracks that end (start) more than :data:`EDGE_FRAMES` from the window's end (start)."""
    end = tracks.start + tracks.length
    deaths = int(np.sum(end < frames - EDGE_FRAMES))
    births = int(np.sum(tracks.start > EDGE_FRAMES))
    lived = max(int(tracks.length.sum()), 1)
    return 1.0 - deaths / lived, births / max(frames - EDGE_FRAMES, 1)


@dataclass
class Calibration:
    """The result: fitted ``values`` (sensor, ``q``, ``p_survival``, ``birth_rate``) and ``stderr``, the
    likelihood of the last M-step before and after (``loglik_before``, ``loglik_after``), the negative
    log-likelihood per detection over every M-step's iterations (``trace``), the window, region, number of
    tracks used, the share of the frames strictly inside the tracks' lives with a detection
    (``detected_share``: what p_D should come near), and seconds."""

    values: dict[str, float]
    stderr: dict[str, float]
    loglik_before: float
    loglik_after: float
    trace: list[float]
    frames: tuple[int, int]
    region: tuple[float, float, float, float]
    detections: int
    velocities: bool
    tracks: int
    detected_share: float = float("nan")
    iterations: list[dict] = field(default_factory=list)
    seconds: float = 0.0


START = {"sigma": 1.0, "p_detection": 0.9, "clutter_density": 1e-4, "velocity_sigma": 1.5,
         "clutter_velocity_sigma": 5.0, "q": 2.0}
"""The tracker's built-in sensor (τ: none built in; 5 px/frame), the first E-step's but for σ and σ_v
(:func:`initial_sigma`) and κ (:func:`initial_values`)."""
PAIR_RADIUS = 20.0


def initial_sigma(data: DetectionFrames, radius: float = PAIR_RADIUS, rounds: int = 30) -> float:
    """A first σ from consecutive frames: the distance ``d`` from each detection (moved by its velocity where
    given) to its nearest detection of the next frame within ``radius`` is a mixture of a Rayleigh of scale
    ``s`` (a target's two detections; ``s² = 2σ² + σ_v²`` with velocities, taken as ``3σ²``, else ``2σ²``) and
    a density rising as ``d`` (an unrelated detection), fitted by EM."""
    d = []
    for k in range(len(data.positions) - 1):
        a, b = data.positions[k], data.positions[k + 1]
        if not len(a) or not len(b):
            continue
        moved = a if data.velocities is None else a + data.velocities[k]
        dist, _ = cKDTree(b).query(moved, distance_upper_bound=radius)
        d.append(dist[np.isfinite(dist)])
    d = np.concatenate(d) if d else np.zeros(0)
    if d.size < 10:
        return START["sigma"]
    s2, share = 4.0, 0.5
    for _ in range(rounds):
        target = share * d / s2 * np.exp(-d ** 2 / (2 * s2))
        other = (1 - share) * 2 * d / radius ** 2
        r = target / np.maximum(target + other, 1e-300)
        share = float(r.mean())
        s2 = float(np.sum(r * d ** 2) / max(2 * np.sum(r), 1e-12))
    return math.sqrt(s2 / (3.0 if data.velocities is not None else 2.0))


def initial_values(data: DetectionFrames) -> dict[str, float]:
    """The first E-step's sensor: :data:`START` with σ and σ_v from :func:`initial_sigma`, and κ from the
    cells of the whole region (:func:`~torchtrack.tuning.background.measure_background` with no track)."""
    values = dict(START)
    values["sigma"] = values["velocity_sigma"] = initial_sigma(data)
    bg = measure_background(data.positions, data.velocities, data.region, np.zeros((0, 2)))
    if bg is not None:
        values["clutter_density"] = bg.clutter_density
        if bg.clutter_velocity_sigma is not None:
            values["clutter_velocity_sigma"] = bg.clutter_velocity_sigma
    return values


def calibrate_sensor(data: DetectionFrames, tracker_config: Callable[[dict], dict],
                     iterations: int = ITERATIONS,
                     progress: Callable[[str], None] | None = None
                     ) -> tuple[Calibration, Tracks, torch.Tensor]:
    """EM of the module docstring over ``data``; ``tracker_config(values)`` is the enhanced GM-PHD's
    configuration for an estimate (the first E-step's from :func:`initial_values`). Returns the calibration,
    the last E-step's tracks and their smoothed means ``(B, T, 4)``."""
    t0 = time.perf_counter()
    values = initial_values(data)
    velocities = data.velocities is not None
    trace: list[float] = []
    history = []
    config = tracker_config(values)
    per_track_q = None
    stderr: dict[str, float] = {}
    for it in range(iterations):
        found = run_tracker(data, config, None if progress is None else f"E-step {it + 1}")
        radius = 3.0 * max(values["sigma"], 1.0)
        tracks = associate(data, found, radius)
        if tracks.z.shape[0] == 0:
            raise NoTracks("calibration: the tracker confirmed no track of 5 detections or more; "
                           "the detections hold no targets it can follow")
        vs = values["velocity_sigma"] if velocities else None
        if per_track_q is None or len(per_track_q) != tracks.z.shape[0]:
            values["q"], per_track_q = fit_q(tracks, values["sigma"], vs)
        sm = smooth(tracks.z, per_track_q, values["sigma"], vs)
        alive = torch.arange(tracks.z.shape[1])[None, :] < torch.from_numpy(tracks.length)[:, None]
        bg = measure_background(data.positions, data.velocities, data.region, sm.mean[..., :2][alive].numpy())
        if bg is not None:
            values["clutter_density"] = bg.clutter_density
            stderr["clutter_density"] = bg.clutter_density_stderr
            if velocities:
                values["clutter_velocity_sigma"] = bg.clutter_velocity_sigma
                stderr["clutter_velocity_sigma"] = bg.clutter_velocity_sigma_stderr
        pairs = sensor_pairs(data, tracks, sm.loo_mean, sm.loo_state_cov, 4.0 * max(values["sigma"], 1.0) + 2.0,
                             values["clutter_density"], values.get("clutter_velocity_sigma") if velocities else None)
        inner = [tracks.detected[b, 1:n - 1] for b, n in enumerate(tracks.length.tolist())]
        seen = sum(int(x.sum()) for x in inner) / max(sum(x.numel() for x in inner), 1)
        values["p_detection"] = min(max(seen, 0.05), 0.99)
        pairs.others = other_tracks(to_theta(values, velocities), pairs)
        est = max((fit_sensor_likelihood(pairs, {**values, "p_detection": start})
                   for start in (min(max(seen, 0.05), 0.99), 0.5, 0.9)), key=lambda e: e.loglik_after)
        trace += est.trace
        values.update(est.values)
        stderr.update(est.stderr)
        values["q"], per_track_q = fit_q(tracks, values["sigma"], values["velocity_sigma"] if velocities else None)
        values["p_survival"], values["birth_rate"] = life_rates(tracks, len(data.positions))
        history.append({"iteration": it + 1, "tracks": int(tracks.z.shape[0]), **{k: round(x, 6) for k, x in
                                                                                  values.items()}})
        if progress is not None:
            progress(f"iteration {it + 1}/{iterations}: {tracks.z.shape[0]} tracks, " +
                     ", ".join(f"{k} {x:.4g}" for k, x in values.items()))
        config = tracker_config(values)
    if not velocities:
        values.pop("velocity_sigma", None)
        values.pop("clutter_velocity_sigma", None)
    cal = Calibration(values=values, stderr=stderr, loglik_before=est.loglik_before, loglik_after=est.loglik_after,
                      trace=trace, frames=(data.first, data.last), region=data.region, detections=data.count,
                      velocities=velocities, tracks=int(tracks.z.shape[0]), detected_share=seen,
                      iterations=history,
                      seconds=time.perf_counter() - t0)
    return cal, tracks, sm.mean
