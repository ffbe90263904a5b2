"""``torchtrack bench gmphd``: GM-PHD steps per second against a per-component NumPy implementation.

Workloads (filter only; measurements generated beforehand):

- ``tutorial`` — Stone Soup's GM-PHD tutorial setting: 10 targets, 100 steps, clutter 10 per scan
  uniform in [−200, 200]², p_D 0.9 (Stone Soup's own GM-PHD runs it at 5–7.5 steps/s on this machine);
- ``wpafb`` — a WPAFB-scale frame: 100 targets and about 150 measurements per frame (90 detections and
  60 clutter points in 1000 × 1000 px).

Both implementations run the same labelled GM-PHD: prediction, measurement-driven birth (eq. 4–5 of
Aguilar et al. 2023, births at rest), the full update with χ² gating, pruning, greedy merging, capping
and extraction (the ``labelled-gmphd`` tracker). The reference loops over components and measurements
like Stone Soup's does; it is timed on fewer steps. The enhanced tracker (label fix, velocity map,
detector velocities) is timed too and reported as ``enhanced_per_s``.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from torchtrack.bench._timing import BenchResult, best_time, format_result
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.gaussian import chi2_quantile

WORKLOADS = {
    # targets, steps, clutter per scan, region side (px), speed std (px/step), p_D, sigma, q
    "tutorial": dict(targets=10, steps=100, clutter=10.0, low=-200.0, high=200.0, speed=1.0, pd=0.9, sigma=1.0, q=0.3),
    "wpafb": dict(targets=100, steps=100, clutter=60.0, low=0.0, high=1000.0, speed=5.0, pd=0.9, sigma=1.0, q=1.0),
}

FILTER = dict(p_survival=0.99, clutter_density=None, gate_probability=0.999, prune_threshold=5e-3,
              merge_threshold=9.0, capacity=1024, extract_threshold=0.5)
BIRTH = dict(birth_weight=0.05, sigma_pos=2.0, sigma_vel_unknown=8.0, distance_threshold=5.0, suppress_weight=0.05)


def scenario(w: dict, steps: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Measurements ``(M, 2)`` and detector velocities ``(M, 2)`` per step: CV targets reflected at the
    region's edges, detected with ``p_D``, noise ``sigma``, Poisson clutter uniform in the region."""
    rng = np.random.default_rng(seed)
    lo, hi = w["low"], w["high"]
    pos = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (w["targets"], 2))
    vel = rng.normal(0.0, w["speed"], (w["targets"], 2))
    out = []
    for _ in range(steps):
        vel = vel + rng.normal(0.0, math.sqrt(w["q"]) * 0.3, vel.shape)
        pos = pos + vel
        vel = np.where((pos < lo) | (pos > hi), -vel, vel)
        pos = np.clip(pos, lo, hi)
        det = rng.random(w["targets"]) < w["pd"]
        z = pos[det] + rng.normal(0.0, w["sigma"], (int(det.sum()), 2))
        v = vel[det] + rng.normal(0.0, 1.0, z.shape)
        nc = rng.poisson(w["clutter"])
        z = np.concatenate([z, rng.uniform(lo, hi, (nc, 2))])
        v = np.concatenate([v, rng.normal(0.0, 1.0, (nc, 2))])
        out.append((z, v))
    return out


def tracker_config(w: dict) -> dict:
    f = dict(FILTER, q=w["q"], sigma=w["sigma"], p_detection=w["pd"],
             clutter_density=w["clutter"] / (w["high"] - w["low"]) ** 2)
    return {"filter": f, "birth": dict(BIRTH), "dtype": "float32"}


# --------------------------------------------------------------------------- NumPy reference
class ReferenceGMPHD:
    """A straightforward per-component labelled GM-PHD in NumPy (one Python object per component, loops
    over components and measurements, as in Stone Soup): the same recursion as ``labelled-gmphd``."""

    def __init__(self, cfg: dict):
        f, b = cfg["filter"], cfg["birth"]
        self.F = np.block([[np.eye(2), np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
        self.Q = f["q"] * np.block([[np.eye(2) / 3, np.eye(2) / 2], [np.eye(2) / 2, np.eye(2)]])
        self.H = np.hstack([np.eye(2), np.zeros((2, 2))])
        self.R = f["sigma"] ** 2 * np.eye(2)
        self.ps, self.pd, self.kappa = f["p_survival"], f["p_detection"], f["clutter_density"]
        self.gate = chi2_quantile(f["gate_probability"], 2)
        self.prune, self.U, self.cap, self.extract = (f["prune_threshold"], f["merge_threshold"], f["capacity"],
                                                      f["extract_threshold"])
        self.bw, self.TB, self.suppress = b["birth_weight"], b["distance_threshold"], b["suppress_weight"]
        self.Pb = np.diag([b["sigma_pos"] ** 2] * 2 + [b["sigma_vel_unknown"] ** 2] * 2)
        self.comps: list[list] = []    # [w, m, P, label]
        self.next_label = 1

    def step(self, z: np.ndarray) -> list[tuple[int, np.ndarray]]:
        F, Q, H, R = self.F, self.Q, self.H, self.R
        pred = [[self.ps * w, F @ m, F @ P @ F.T + Q, lab] for w, m, P, lab in self.comps]
        birth_z = [zj for zj in z
                   if all(not (w >= self.suppress and np.linalg.norm(H @ m - zj) <= self.TB) for w, m, _, _ in pred)]
        post = [[(1 - self.pd) * w, m, P, lab] for w, m, P, lab in pred]
        pre = []
        for w, m, P, lab in pred:
            S = H @ P @ H.T + R
            Si = np.linalg.inv(S)
            K = P @ H.T @ Si
            Pu = (np.eye(4) - K @ H) @ P
            pre.append((w, m, Pu, lab, H @ m, S, Si, K))
        for zj in z:
            hyps = []
            for w, m, Pu, lab, zh, S, Si, K in pre:
                nu = zj - zh
                d2 = nu @ Si @ nu
                if d2 <= self.gate:
                    g = math.exp(-0.5 * d2) / (2 * math.pi * math.sqrt(np.linalg.det(S)))
                    hyps.append([self.pd * w * g, m + K @ nu, Pu, lab])
            total = self.kappa + sum(h[0] for h in hyps)
            for h in hyps:
                h[0] /= total
            post.extend(hyps)
        post = [c for c in post if c[0] > self.prune]
        merged = []
        while post:
            j = max(range(len(post)), key=lambda i: post[i][0])
            _, mj, _, lj = post[j]
            group, rest = [], []
            for c in post:
                d = c[1] - mj
                (group if d @ np.linalg.solve(c[2], d) <= self.U else rest).append(c)
            ws = sum(c[0] for c in group)
            mu = sum(c[0] * c[1] for c in group) / ws
            P = sum(c[0] * (c[2] + np.outer(c[1] - mu, c[1] - mu)) for c in group) / ws
            merged.append([ws, mu, P, lj])
            post = rest
        merged = sorted(merged, key=lambda c: -c[0])[: self.cap]
        best: dict[int, tuple[float, np.ndarray]] = {}
        for w, m, _, lab in merged:
            if w > self.extract and (lab not in best or w > best[lab][0]):
                best[lab] = (w, m[:2])
        for zj in birth_z:
            merged.append([self.bw, np.array([zj[0], zj[1], 0.0, 0.0]), self.Pb.copy(), self.next_label])
            self.next_label += 1
        self.comps = merged[: self.cap]
        return [(lab, m) for lab, (_, m) in best.items()]


# --------------------------------------------------------------------------- timing
def _time_torch(name: str, cfg: dict, frames: list, with_velocity: bool, repeats: int
                ) -> tuple[float, float, float]:
    """Best-of-``repeats`` wall-clock steps/s, the matching process-CPU-time steps/s, mean estimates."""
    data = [(torch.from_numpy(z).float(), torch.from_numpy(v).float() if with_velocity else None) for z, v in frames]
    best, best_cpu, mean_count = float("inf"), float("inf"), 0.0
    for _ in range(repeats + 1):     # the first pass warms up
        tracker = make_tracker(name, cfg)
        count = 0
        t0, c0 = time.perf_counter(), time.process_time()
        for k, (z, v) in enumerate(data, start=1):
            ids, _ = tracker.step(k, z, v)
            count += ids.numel()
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
        mean_count = count / len(data)
    return len(data) / best, len(data) / best_cpu, mean_count


def op_overhead_us(n: int = 20000) -> float:
    """Process-CPU microseconds of one tiny torch operation (``a + b`` on 4-element tensors), measured now:
    the per-operation cost that bounds a per-frame filter on this machine at this moment."""
    a, b = torch.ones(4), torch.ones(4)
    c0 = time.process_time()
    for _ in range(n):
        a + b
    return 1e6 * (time.process_time() - c0) / n


def measure(wname: str, overhead_us: float, steps: int | None = None, reference_steps: int = 20, repeats: int = 5,
            seed: int = 0) -> BenchResult:
    """Time the labelled and the enhanced GM-PHD (best of ``repeats`` passes over ``steps`` steps; None: the
    workload's) and the NumPy reference (``reference_steps``) on the workload ``wname`` of ``WORKLOADS``;
    ``overhead_us`` (:func:`op_overhead_us`) is reported with them."""
    w = WORKLOADS[wname]
    steps = steps or w["steps"]
    frames = scenario(w, steps, seed)
    cfg = tracker_config(w)
    ours, ours_cpu, card = _time_torch("labelled-gmphd", cfg, frames, False, repeats)
    enhanced, enhanced_cpu, card_e = _time_torch("gmphd", cfg, frames, True, repeats)
    ref_steps = min(reference_steps, steps)
    ref = ReferenceGMPHD(cfg)
    reference = ref_steps / best_time(lambda: [ref.step(z) for z, _ in frames[:ref_steps]], repeats=1, warmup=0)
    meas = float(np.mean([z.shape[0] for z, _ in frames]))
    workload = (f"{wname}: {w['targets']} targets, {steps} steps, ~{meas:.0f} measurements/step "
                f"(clutter {w['clutter']:g}/scan), p_D {w['pd']}; labelled GM-PHD, float32, "
                f"{torch.get_num_threads()} thread(s)")
    return BenchResult(workload, ours, f"NumPy per-component GM-PHD ({ref_steps} steps)", reference, "steps",
                       {"enhanced_per_s": enhanced, "ours_cpu_per_s": ours_cpu, "op_overhead_us": overhead_us,
                        "enhanced_cpu_per_s": enhanced_cpu, "mean_estimates": card,
                        "mean_estimates_enhanced": card_e, "reference_steps": ref_steps})


def format_workload(wname: str, r: BenchResult) -> str:
    """One workload's table and the enhanced tracker's rates, as ``torchtrack bench gmphd`` prints them."""
    e = r.extra
    return "\n".join([
        "", format_result(r),
        f"per process CPU second (load-independent): labelled {e['ours_cpu_per_s']:,.0f} steps/s, enhanced "
        f"{e['enhanced_cpu_per_s']:,.0f} steps/s",
        f"enhanced GM-PHD (label fix, velocity map, detector velocity): {e['enhanced_per_s']:,.0f} steps/s; "
        f"mean estimates/step: labelled {e['mean_estimates']:.1f}, enhanced {e['mean_estimates_enhanced']:.1f}, "
        f"targets {WORKLOADS[wname]['targets']}"])
