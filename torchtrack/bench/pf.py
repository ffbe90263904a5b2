"""``torchtrack bench pf``: throughput of the JTC particle-filter bank (particle-steps per second).

Workload: the JTC paper's bank (2 classes × 5 modes, range–bearing radar, speed likelihoods,
systematic resampling at every scan) on the paper's trajectory, ``--runs`` runs × 2 classes ×
``--particles`` particles × ``--scans`` scans, float32 or float64. Timed in the same process:

* **ours** — :class:`torchtrack.filters.particle.jtc.MultipleModelParticleFilter`, all runs one batch;
  best of ``--repeats`` whole passes (after one warm-up pass), random draws included;
* **reference** — the same algorithm written in vectorised NumPy (all runs and classes batched,
  systematic resampling by one ``np.searchsorted`` over the concatenated rows).

Both run on ``--threads`` threads (torch intra-op; NumPy's elementwise code is single-threaded).
The mean final probability of the true class is printed for both as a sanity check.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchtrack.bench._timing import BenchResult, best_time, cpu_time, format_result, load_average
from torchtrack.filters.particle.jtc import MultipleModelParticleFilter, paper_bank
from torchtrack.sim.jtc_trajectory import jtc_trajectory, simulate_measurements
from torchtrack.threads import TRACKER_THREADS, torch_threads

PRIOR_STD = (150.0, 150.0, 20.0, 20.0)


def numpy_bank(bank: MultipleModelParticleFilter, z: np.ndarray, mean: np.ndarray, std: np.ndarray, dt: float,
               rng: np.random.Generator) -> np.ndarray:
    """The bank's algorithm in NumPy; ``z (K, R, 2)``; returns the class probabilities ``(K, R, C)``."""
    dtype = z.dtype
    C, M, N = bank.num_classes, bank.num_modes, bank.num_particles
    R = z.shape[1]
    control = torch.cat([m.controls for m in bank.motions]).detach().numpy().astype(dtype).T      # (2, C·M)
    sigma = torch.cat([m.sigma() for m in bank.motions]).detach().numpy().astype(dtype)         # (C·M,)
    cum = np.cumsum(bank.transition.numpy(), -1).reshape(C * M, M).astype(dtype)
    cum[:, -1] = 1.0
    offset = (np.arange(C) * M)[:, None]
    env = bank.speed_envelopes.numpy().astype(dtype)
    radar = bank.measurement
    sensor = radar.sensor_position.numpy().astype(dtype)
    sr, sb = float(radar.sigma_range()), float(radar.sigma_bearing())
    log_norm = -math.log(2 * math.pi * sr * sb)
    x = (mean[:, None, None, :] + rng.standard_normal((R, C, N, 4), dtype=dtype) * std).transpose(3, 0, 1, 2).copy()
    p0 = np.cumsum(bank.initial_mode.numpy(), -1).astype(dtype)                               # (C, M)
    mode = (rng.random((R, C, N, 1), dtype=dtype) > p0[None, :, None, :]).sum(-1)
    log_class = np.log(np.broadcast_to(bank.class_prior.numpy(), (R, C))).astype(dtype)
    speed = np.broadcast_to(np.hypot(mean[:, 2], mean[:, 3])[:, None], (R, C))
    rows = np.arange(R * C).reshape(R, C, 1)
    out = []
    for k in range(1, z.shape[0] + 1):
        eps = rng.standard_normal((2, R, C, N), dtype=dtype)
        u = rng.random((R, C, N, 1), dtype=dtype)
        u_res = rng.random((R, C, 1), dtype=dtype)
        mode = (u > cum[mode + offset]).sum(-1)
        idx = mode + offset
        acc = control[:, idx] + sigma[idx] * eps
        x[:2] += dt * x[2:] + 0.5 * dt * dt * acc
        x[2:] += dt * acc
        dx, dy = x[0] - sensor[0], x[1] - sensor[1]
        nu_r = z[k - 1, :, 0, None, None] - np.hypot(dx, dy)
        nu_b = np.remainder(z[k - 1, :, 1, None, None] - np.arctan2(dx, dy) + np.pi, 2 * np.pi) - np.pi
        ll = -0.5 * ((nu_r / sr) ** 2 + (nu_b / sb) ** 2)
        top = ll.max(-1, keepdims=True)
        w = np.exp(ll - top)
        total = w.sum(-1, keepdims=True)
        log_L = (np.log(total) + top)[..., 0] + log_norm
        if k > bank.warmup:
            lo, hi, g_lo, g_hi = env.T
            log_L = log_L + np.log(g_lo + (g_hi - g_lo) / (hi - lo) * (np.clip(speed, lo, hi) - lo))
        log_class = log_class + log_L
        log_class -= np.logaddexp.reduce(log_class, -1, keepdims=True)
        cdf = np.cumsum(w, -1) / total
        grid = (np.arange(N) + u_res) / N
        anc = np.searchsorted((cdf + rows).ravel(), (grid + rows).ravel(), side="right").reshape(R, C, N)
        anc = np.minimum(anc - rows * N, N - 1)
        x = np.take_along_axis(x, np.broadcast_to(anc, (4, R, C, N)), -1)
        mode = np.take_along_axis(mode, anc, -1)
        class_mean = x.mean(-1)
        speed = np.hypot(class_mean[2], class_mean[3])
        out.append(np.exp(log_class))
    return np.stack(out)


def measure(runs: int = 20, particles: int = 3000, scans: int = 80, dtype: str = "float32",
            threads: int = TRACKER_THREADS, compile: bool = False, repeats: int = 3, seed: int = 0) -> BenchResult:
    """Time the bank (best of ``repeats`` passes, on ``threads`` torch threads; ``compile``: its step
    ``torch.compile``d) and the NumPy reference on the same measurements of ``runs`` runs."""
    with torch_threads(threads):
        torch_dtype = getattr(torch, dtype)
        traj = jtc_trajectory(scans)
        bank = paper_bank(particles)
        if compile:
            bank.kernel = torch.compile(bank.kernel, dynamic=False)
        gen = torch.Generator().manual_seed(seed)
        z = simulate_measurements(traj, bank.measurement, runs, gen).to(torch_dtype)
        mean = traj.states[0].to(torch_dtype).expand(runs, 4)
        std = torch.tensor(PRIOR_STD, dtype=torch_dtype)
        cov = torch.diag(std**2)
        with torch.inference_mode():
            t_ours = best_time(lambda: bank.run(z, mean, cov, traj.dt, gen), repeats)
            ours, c_ours = cpu_time(lambda: bank.run(z, mean, cov, traj.dt, gen))
        rng = np.random.default_rng(seed)
        z_np, mean_np, std_np = z.numpy(), mean.numpy(), std.numpy()
        t_ref = best_time(lambda: numpy_bank(bank, z_np, mean_np, std_np, traj.dt, rng), repeats, warmup=0)
        ref, c_ref = cpu_time(lambda: numpy_bank(bank, z_np, mean_np, std_np, traj.dt, rng))
    steps = runs * bank.num_classes * particles * scans
    extra = {
        "runs": runs, "particles_per_class": particles, "scans": scans, "dtype": dtype,
        "threads": threads, "compiled": compile, "load_average_1min": load_average(),
        "ours_ms_per_scan": 1e3 * t_ours / scans,
        "reference_ms_per_scan": 1e3 * t_ref / scans,
        "ours_cpu_ms_per_scan": 1e3 * c_ours / scans, "reference_cpu_ms_per_scan": 1e3 * c_ref / scans,
        "ours_final_class2_probability": float(ours.class_prob[-1, :, 1].mean()),
        "reference_final_class2_probability": float(ref[-1, :, 1].mean()),
    }
    compiled = ", compiled" if compile else ""
    return BenchResult(f"JTC bank, {runs} runs x 2 classes x {particles} particles x {scans} scans, "
                       f"{dtype}, {threads} thread(s){compiled}", steps / t_ours, "numpy (vectorised, same algorithm)",
                       steps / t_ref, "particle-steps", extra)


def format_report(r: BenchResult) -> str:
    """The table, the times per scan and both final class probabilities."""
    e = r.extra
    return "\n".join([
        format_result(r),
        f"ms per scan (wall): ours {e['ours_ms_per_scan']:.1f}, numpy {e['reference_ms_per_scan']:.1f}; "
        f"(process CPU, one pass): ours {e['ours_cpu_ms_per_scan']:.1f}, numpy {e['reference_cpu_ms_per_scan']:.1f}",
        f"final mean P(class 2): ours {e['ours_final_class2_probability']:.3f}, "
        f"numpy {e['reference_final_class2_probability']:.3f}"])
