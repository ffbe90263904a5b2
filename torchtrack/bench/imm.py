"""``torchtrack bench imm``: a 3-model IMM on ``[x, y, vx, vy]`` for many tracks against FilterPy.

Ours: :class:`~torchtrack.filters.imm.cv.ConstantVelocityIMM` (structured elementwise step, compiled
with ``torch.compile`` unless ``--no-compile``), all tracks at once, float32 by default; a full cycle
per step: interaction, three model-matched predictions and updates, mode update, combination.
Reference: FilterPy's ``IMMEstimator`` (three ``KalmanFilter``s with the same models), one object
per track, on ``--reference-tracks`` tracks (test-only dependency, imported here only). Rates are
track-steps per second, both timed in the same run: per wall-clock second (the design's
``ours_per_s``/``reference_per_s``) and per CPU second of this process (``*_per_cpu_s``), which is
what a run on an otherwise idle machine would see per core when the machine is shared.
"""

from __future__ import annotations

import time
from functools import partial

import torch

from torchtrack.bench._timing import BenchResult, best_time, cpu_time, format_result
from torchtrack.errors import TorchtrackError
from torchtrack.filters.imm.cv import ConstantVelocityIMM
from torchtrack.models import LinearPosition, ModeControlInput
from torchtrack.threads import TRACKER_THREADS, torch_threads

G = 9.81
CONTROLS = [[0.0, 0.0], [0.0, 3 * G], [0.0, -G]]
TRANSITION = [[0.95, 0.05, 0.0], [0.1, 0.8, 0.1], [0.0, 0.05, 0.95]]


def _model(dtype: torch.dtype) -> ConstantVelocityIMM:
    motion = ModeControlInput(CONTROLS, [0.2, 0.2, 0.2], learnable=False)
    meas = LinearPosition(2, sigma=10.0, learnable=False)
    return ConstantVelocityIMM(motion, meas, torch.tensor(TRANSITION)).to(dtype)


def _data(n: int, steps: int, gen: torch.Generator, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Straight tracks at 25 m/s in random directions, measured with 10 m noise: ``(steps, n, 2)``."""
    start = 1000 * torch.randn(n, 2, generator=gen, dtype=torch.float64)
    heading = 2 * torch.pi * torch.rand(n, generator=gen, dtype=torch.float64)
    vel = 25 * torch.stack([heading.cos(), heading.sin()], -1)
    t = torch.arange(1, steps + 1, dtype=torch.float64)[:, None, None]
    z = start + t * vel + 10 * torch.randn(steps, n, 2, generator=gen, dtype=torch.float64)
    return z.to(dtype), torch.cat([start, vel], -1).to(dtype)


def filterpy_rate(z: torch.Tensor, x0: torch.Tensor, model: ConstantVelocityIMM) -> tuple[float, float, torch.Tensor]:
    """Track-steps per wall-clock second and per CPU second of FilterPy's ``IMMEstimator``, one estimator
    per track (float64 numpy), and its final combined estimates ``(n, 4)``."""
    try:
        import numpy as np
        from filterpy.kalman import IMMEstimator, KalmanFilter
    except ImportError as exc:
        raise TorchtrackError("the reference needs FilterPy (a test-only dependency): "
                              "pip install 'torchtrack-mtt[test]' or pip install filterpy") from exc
    m = model.double()
    F = m.motion.transition_matrix(1.0).numpy()
    Gm = m.motion.gain(1.0).numpy()
    H = m.measurement.matrix().detach().numpy()
    R = m.measurement.noise_cov().detach().numpy()
    M = np.asarray(TRANSITION)
    P0 = np.diag([100.0, 100.0, 25.0, 25.0])
    zs = z.double().numpy()
    u = np.ones((1, 1))

    def make(x):
        filters = []
        for j in range(m.num_models):
            kf = KalmanFilter(dim_x=4, dim_z=2, dim_u=1)
            kf.F, kf.H, kf.R = F, H, R
            kf.Q = m.motion.process_noise(1.0, torch.tensor(j)).detach().numpy()
            kf.B = (Gm @ m.motion.controls[j].numpy()).reshape(4, 1)
            kf.x = x.reshape(4, 1).copy()
            kf.P = P0.copy()
            filters.append(kf)
        return IMMEstimator(filters, np.full(m.num_models, 1.0 / m.num_models), M)

    imms = [make(x) for x in x0.double().numpy()]
    t0, c0 = time.perf_counter(), time.process_time()
    for k in range(zs.shape[0]):
        for i, imm in enumerate(imms):
            imm.predict(u)
            imm.update(zs[k, i].reshape(2, 1))
    n = len(imms) * zs.shape[0]
    rates = n / (time.perf_counter() - t0), n / (time.process_time() - c0)
    return rates[0], rates[1], torch.as_tensor(np.stack([imm.x.ravel() for imm in imms]))


def measure(tracks: int = 100_000, steps: int = 20, reference_tracks: int = 100, dtype: str = "float32",
            threads: int = TRACKER_THREADS, compile: bool = True, seed: int = 0) -> BenchResult:
    """Time our IMM on ``tracks`` tracks x ``steps`` steps (best of 3, on ``threads`` torch threads, compiled
    or eager) and FilterPy on the first ``reference_tracks`` of them; ``extra`` holds the CPU-time rates and
    the largest deviation of the final estimates from FilterPy's."""
    with torch_threads(threads):
        torch_dtype = getattr(torch, dtype)
        gen = torch.Generator().manual_seed(seed)
        z, x0 = _data(tracks, steps, gen, torch_dtype)
        model = _model(torch_dtype)
        init = model.initial_state(x0, torch.diag(torch.tensor([100.0, 100.0, 25.0, 25.0], dtype=torch_dtype)))
        with torch.no_grad():
            warm = best_time(partial(model.run_packed, z[:2], init, 1.0, compile=compile), 1, 0)   # compilation
            seconds = best_time(partial(model.run_packed, z, init, 1.0, compile=compile), repeats=3, warmup=0)
            (_, means, _), cpu = cpu_time(partial(model.run_packed, z, init, 1.0, compile=compile))
        n_ref = min(reference_tracks, tracks)
        ref, ref_cpu, ref_x = filterpy_rate(z[:, :n_ref], x0[:n_ref], _model(torch.float64))
        deviation = float((means[-1, :n_ref].double() - ref_x).abs().max())
        workload = (f"IMM, 3 models (CV + lateral inputs 0, 3g, -g), [x, y, vx, vy], {tracks} tracks x "
                    f"{steps} steps, {dtype}, {torch.get_num_threads()} threads, "
                    f"{'torch.compile' if compile else 'eager'}")
    return BenchResult(workload, tracks * steps / seconds, f"filterpy IMMEstimator per track ({n_ref} tracks)", ref,
                       "track-steps", {"ms_per_step": 1e3 * seconds / steps, "warmup_s": warm,
                                       "ours_per_cpu_s": tracks * steps / cpu, "reference_per_cpu_s": ref_cpu,
                                       "max_abs_deviation_from_reference": deviation})


def format_report(r: BenchResult, reference_tracks: int) -> str:
    """The table and the CPU-time rates and deviation over the ``reference_tracks`` FilterPy ran."""
    e = r.extra
    return "\n".join([
        format_result(r),
        f"per CPU second (all threads; robust to other load): torchtrack {e['ours_per_cpu_s']:,.0f}, "
        f"reference {e['reference_per_cpu_s']:,.0f} track-steps",
        f"final combined estimates of the {reference_tracks} reference tracks: max |ours - FilterPy| = "
        f"{e['max_abs_deviation_from_reference']:.2e}"])
