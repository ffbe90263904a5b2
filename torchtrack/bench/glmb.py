"""``torchtrack bench glmb``: frames/s of the ``glmb`` tracker at WPAFB scale against a NumPy δ-GLMB that loops
over hypotheses and tracks as the published codes do (:mod:`torchtrack.bench.glmb_reference`), in the same run.

Workload: ``bench gmphd``'s WPAFB-scale frames (:func:`torchtrack.bench.gmphd.scenario`): 100 vehicles with
constant-velocity motion in 1000 × 1000 px, detected with p_D 0.9 and σ 1 px, Poisson clutter of mean 60 —
about 150 measurements per frame — with the detector's velocity (noise 1 px/frame) used or not (``velocities``).
Both trackers take the ``glmb`` defaults (:class:`~torchtrack.filters.trackers.options.GLMBConfig`) except the
clutter density, set to the workload's, and ``velocity_sigma`` (1 px/frame with velocities, else None). Each
starts empty and runs ``warmup`` frames untimed (its tracks are born and confirmed), then the next frames are
timed one step at a time: ``frames`` of ours, ``reference_frames`` (fewer) of the reference; rates are per frame.
Ours runs on ``threads`` torch threads; the reference is single-threaded NumPy/Python. Besides the rates, the
hypotheses, table rows, groups and estimated tracks per timed frame of each, and the reference's Gibbs draws.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from torchtrack.bench._timing import BenchResult, format_result, load_average
from torchtrack.bench.glmb_reference import ReferenceGLMB
from torchtrack.bench.gmphd import WORKLOADS, scenario
from torchtrack.filters.trackers.options import tracker_config
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.threads import TRACKER_THREADS, torch_threads

DETECTOR_VELOCITY_SIGMA = 1.0   # px/frame: the workload's velocity noise


def workload(targets: int, frames: int, seed: int) -> tuple[dict, list[tuple[np.ndarray, np.ndarray]]]:
    """The WPAFB-scale workload with ``targets`` vehicles (clutter in proportion, 60 per 100): its parameters
    and ``frames`` frames of positions ``(M, 2)`` and detector velocities ``(M, 2)``."""
    base = WORKLOADS["wpafb"]
    w = dict(base, targets=targets, clutter=base["clutter"] * targets / base["targets"])
    return w, scenario(w, frames, seed)


class _Clock:
    """Wall and process CPU seconds summed over the timed calls."""

    def __init__(self):
        self.wall = self.cpu = 0.0

    def __call__(self, fn, *args):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn(*args)
        self.wall += time.perf_counter() - w0
        self.cpu += time.process_time() - c0
        return out


def measure(targets: int = 100, warmup: int = 10, frames: int = 100, reference_frames: int = 20,
            velocities: bool = False, threads: int = TRACKER_THREADS, seed: int = 0) -> BenchResult:
    """Time our ``glmb`` tracker and the NumPy reference on the same frames (module docstring)."""
    w, scene = workload(targets, warmup + max(frames, reference_frames), seed)
    options = {"clutter_density": w["clutter"] / (w["high"] - w["low"]) ** 2, "seed": seed,
               "velocity_sigma": DETECTOR_VELOCITY_SIGMA if velocities else None}
    config = tracker_config("glmb", options)
    with torch_threads(threads):
        ours, clock = make_tracker("glmb", options), _Clock()
        hyps, rows, groups, reported = [], [], [], []
        for k, (z, v) in enumerate(scene[:warmup + frames]):
            zt, vt = torch.from_numpy(z), torch.from_numpy(v) if velocities else None
            ids, _ = clock(ours.step, k + 1, zt, vt) if k >= warmup else ours.step(k + 1, zt, vt)
            if k >= warmup:
                hyps.append(ours.state.hyp.shape[0])
                rows.append(ours.state.mean.shape[0])
                groups.append(int(ours.state.group.max()) + 1)
                reported.append(ids.shape[0])
        n_threads = torch.get_num_threads()
    reference, ref_clock = ReferenceGLMB(config, seed, velocities=velocities), _Clock()
    ref_hyps, ref_rows, ref_estimated = [], [], []
    for k, (z, v) in enumerate(scene[:warmup + reference_frames]):
        if k == warmup:
            reference.draws = 0
        labels, _, _ = ref_clock(reference.step, k + 1, z, v) if k >= warmup else reference.step(k + 1, z, v)
        if k >= warmup:
            ref_hyps.append(len(reference.state.hypotheses))
            ref_rows.append(len(reference.state.table))
            ref_estimated.append(len(labels))
    measurements = float(np.mean([z.shape[0] for z, _ in scene[warmup:]]))
    return BenchResult(
        f"glmb tracker, {targets} vehicles, {measurements:.0f} measurements/frame (WPAFB scale), "
        f"{'positions and detector velocities' if velocities else 'positions only'}, {warmup} warm-up frames",
        frames / clock.wall, "numpy per-hypothesis GLMB (no groups)", reference_frames / ref_clock.wall, "frames",
        {"frames": frames, "reference_frames": reference_frames, "cpu_per_s": frames / clock.cpu,
         "reference_cpu_per_s": reference_frames / ref_clock.cpu, "ms_per_frame": 1e3 * clock.wall / frames,
         "reference_ms_per_frame": 1e3 * ref_clock.wall / reference_frames,
         "cpu_ratio": (frames / clock.cpu) / (reference_frames / ref_clock.cpu),
         "measurements_per_frame": measurements, "hypotheses_per_frame": float(np.mean(hyps)),
         "groups_per_frame": float(np.mean(groups)), "table_rows_per_frame": float(np.mean(rows)),
         "reported_tracks_per_frame": float(np.mean(reported)),
         "reference_hypotheses_per_frame": float(np.mean(ref_hyps)),
         "reference_table_rows_per_frame": float(np.mean(ref_rows)),
         "reference_estimated_tracks_per_frame": float(np.mean(ref_estimated)),
         "reference_gibbs_draws_per_frame": reference.draws / reference_frames,
         "cap_hits": ours.cap_hits, "threads": n_threads, "load_average": load_average()})


def format_report(r: BenchResult) -> str:
    """Per-frame costs and sizes of both, then the rate table."""
    e = r.extra
    return "\n".join([
        f"ours: {e['ms_per_frame']:.1f} ms/frame over {e['frames']} frames ({e['cpu_per_s']:.1f} frames per CPU "
        f"second, {e['threads']} thread(s)); {e['hypotheses_per_frame']:.0f} hypotheses in "
        f"{e['groups_per_frame']:.0f} groups, {e['table_rows_per_frame']:.0f} table rows, "
        f"{e['reported_tracks_per_frame']:.0f} reported tracks per frame",
        f"reference: {e['reference_ms_per_frame']:.1f} ms/frame over {e['reference_frames']} frames "
        f"({e['reference_cpu_per_s']:.2f} frames per CPU second); {e['reference_hypotheses_per_frame']:.0f} "
        f"hypotheses, {e['reference_table_rows_per_frame']:.0f} table rows, "
        f"{e['reference_estimated_tracks_per_frame']:.0f} estimated tracks, "
        f"{e['reference_gibbs_draws_per_frame']:,.0f} Gibbs draws per frame",
        f"CPU-time ratio {e['cpu_ratio']:.1f}x",
        format_result(r)])
