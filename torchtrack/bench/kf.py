"""``torchtrack bench kf``: batched Kalman filter throughput (track-steps per second).

Workload: 2-D nearly-constant-velocity targets (state ``[x, y, vx, vy]``), position measurements,
float32, ``--tracks`` tracks × ``--steps`` steps. Timed in the same run:

* **ours** — :meth:`KalmanFilter.run` with ``engine="axes"`` (the axis-decoupled engine,
  :mod:`torchtrack.filters.kalman.axes`, compiled; final posterior only, ``history=False``);
* **general path** — :meth:`KalmanFilter.run`'s default engine (lanes) with full 4×4 matrices (reported as
  extras: ``general_path_per_s`` compiled unless ``--no-compile``, ``general_path_eager_per_s``,
  ``general_path_per_cpu_s``; ``batch_first_loop_per_s`` is the batch-first predict/update loop that
  was the general path before the batch-last layout);
* **reference** — a plain batched NumPy implementation of the same equations (4×4 matrices,
  ``np.linalg.solve`` for the gain);
* **per-track loop** — FilterPy's ``KalmanFilter`` one track at a time (as FilterPy users run it)
  on ``--loop-tracks`` tracks, if FilterPy is installed.
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np
import torch

from torchtrack.bench._timing import BenchResult, best_time, format_result
from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter
from torchtrack.models import ConstantVelocity, LinearPosition
from torchtrack.threads import TRACKER_THREADS, torch_threads

DT, Q, SIGMA = 1.0, 0.05, 1.0


def _numpy_reference(z: np.ndarray, x0: np.ndarray, P0: np.ndarray, F, Qm, H, R) -> tuple[np.ndarray, np.ndarray]:
    x, P = x0.copy(), P0.copy()
    ll = np.zeros(x.shape[0], dtype=x.dtype)
    for k in range(z.shape[0]):
        x = x @ F.T
        P = F @ P @ F.T + Qm
        S = H @ P @ H.T + R
        nu = z[k] - x @ H.T
        PHt = P @ H.T
        K = np.linalg.solve(S, PHt.transpose(0, 2, 1)).transpose(0, 2, 1)
        x = x + np.einsum("nij,nj->ni", K, nu)
        P = P - K @ S @ K.transpose(0, 2, 1)
        sol = np.linalg.solve(S, nu[..., None])[..., 0]
        ll -= 0.5 * ((nu * sol).sum(-1) + np.log(np.linalg.det(S)) + 2 * np.log(2 * np.pi))
    return x, ll


def _filterpy_loop(z: np.ndarray, x0: np.ndarray, P0: np.ndarray, F, Qm, H, R) -> None:
    from filterpy.kalman import KalmanFilter as FPKalman

    for i in range(z.shape[1]):
        f = FPKalman(dim_x=4, dim_z=2)
        f.x, f.P, f.F, f.Q, f.H, f.R = x0[i].copy(), P0[i].copy(), F, Qm, H, R
        for k in range(z.shape[0]):
            f.predict()
            f.update(z[k, i])


def measure(tracks: int = 100_000, steps: int = 100, general_steps: int = 10, loop_tracks: int = 200,
            compile: bool = True, seed: int = 0, threads: int = TRACKER_THREADS) -> BenchResult:
    """Time the axis-decoupled engine on ``tracks`` x ``steps`` (``compile``: torch.compile'd), the general
    path on ``general_steps`` steps, the NumPy reference and FilterPy's per-track loop on ``loop_tracks``
    tracks (when installed), torch on ``threads`` intra-op threads; the general path's and the loop's rates
    are in ``extra``."""
    with torch_threads(threads):
        return _measure(tracks, steps, general_steps, loop_tracks, compile, seed)


def _measure(tracks: int, steps: int, general_steps: int, loop_tracks: int, compile: bool, seed: int
             ) -> BenchResult:
    gen = torch.Generator().manual_seed(seed)
    N, T = tracks, steps
    dtype = torch.float32
    kf = KalmanFilter(ConstantVelocity(2, q=Q), LinearPosition(2, sigma=SIGMA)).to(dtype)
    truth_v = torch.randn(N, 2, generator=gen, dtype=dtype) * 5
    t = torch.arange(1, T + 1, dtype=dtype)[:, None, None]
    z = (t * truth_v + torch.randn(T, N, 2, generator=gen, dtype=dtype) * SIGMA).contiguous()
    init = GaussianState(torch.zeros(N, 4, dtype=dtype), torch.diag(torch.tensor([10.0, 10, 100, 100])).to(dtype)
                         .expand(N, 4, 4))

    with torch.no_grad():
        ours = partial(kf.run, z, init, DT, compile=compile, engine="axes", history=False)
        warmup_s = best_time(ours, repeats=1, warmup=0)     # the first call, compilation included
        ours_s = best_time(ours, repeats=3, warmup=0)
        Tg = min(general_steps, T)
        general = partial(kf.run, z[:Tg], init, DT, compile=compile)
        general_warmup_s = best_time(general, repeats=1, warmup=0)
        general_s = best_time(general, repeats=5, warmup=0)
        batch_first_s = best_time(partial(kf.run, z[:Tg], init, DT, engine="batch"), repeats=1, warmup=0)
        general_cpu_s = best_time(general, repeats=3, warmup=0, clock=time.process_time)
        general_eager_s = best_time(partial(kf.run, z[:Tg], init, DT), repeats=1, warmup=0) if compile else general_s

    F = kf.motion.transition_matrix(DT).double().numpy()
    Qm = kf.motion.process_noise(DT).detach().double().numpy()
    H = kf.measurement.matrix().double().numpy()
    R = kf.measurement.noise_cov().detach().double().numpy()
    F32, Q32, H32, R32 = (m.astype(np.float32) for m in (F, Qm, H, R))
    z_np = z.numpy()
    x0 = init.mean.numpy().copy()
    P0 = init.cov.numpy().copy()
    Tr = min(T, 10)
    ref_s = best_time(lambda: _numpy_reference(z_np[:Tr], x0, P0, F32, Q32, H32, R32), repeats=1, warmup=0)

    extra = {"tracks": N, "steps": T, "dtype": "float32", "compile": compile, "threads": torch.get_num_threads(),
             "warmup_s": warmup_s,
             "general_path_per_s": N * Tg / general_s,
             "general_path_eager_per_s": N * Tg / general_eager_s,
             "general_path_per_cpu_s": N * Tg / general_cpu_s,
             "batch_first_loop_per_s": N * Tg / batch_first_s,
             "general_warmup_s": general_warmup_s}
    try:
        import filterpy  # noqa: F401

        M = min(loop_tracks, N)
        loop_s = best_time(lambda: _filterpy_loop(z_np[:Tr, :M].astype(np.float64), x0[:M].astype(np.float64),
                                                  P0[:M].astype(np.float64), F, Qm, H, R), repeats=1, warmup=0)
        extra["filterpy_loop_per_s"] = M * Tr / loop_s
        extra["ratio_vs_filterpy_loop"] = (N * T / ours_s) / extra["filterpy_loop_per_s"]
    except ImportError:
        extra["filterpy_loop_per_s"] = None

    return BenchResult(f"KF, 2-D CV + position, {N} tracks x {T} steps, float32", N * T / ours_s,
                       "batched NumPy (same equations, 4x4)", N * Tr / ref_s, "track-steps", extra)


def format_report(r: BenchResult) -> str:
    """The table and the general path's, the batch-first loop's and FilterPy's rates."""
    e = r.extra
    lines = [format_result(r),
             f"general path (KalmanFilter.run, 4x4 matrices{', compiled' if e['compile'] else ''}): "
             f"{e['general_path_per_s']:,.0f} track-steps/s (eager: {e['general_path_eager_per_s']:,.0f}; "
             f"first call {e['general_warmup_s']:.1f} s; {e['general_path_per_cpu_s']:,.0f} per CPU-second)",
             f"batch-first predict/update loop (the previous general path): "
             f"{e['batch_first_loop_per_s']:,.0f} track-steps/s"]
    if e.get("filterpy_loop_per_s"):
        lines.append(f"FilterPy per-track loop: {e['filterpy_loop_per_s']:,.0f} track-steps/s "
                     f"(ours {e['ratio_vs_filterpy_loop']:,.0f}x)")
    lines.append(f"(first call incl. compilation: {e['warmup_s']:.1f} s)")
    return "\n".join(lines)
