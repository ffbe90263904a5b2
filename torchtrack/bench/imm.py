"""``torchtrack bench imm``: a 3-model IMM on ``[x, y, vx, vy]`` for many tracks against FilterPy.

Ours: :class:`~torchtrack.filters.imm_cv.ConstantVelocityIMM` (structured elementwise step, compiled
with ``torch.compile`` unless ``--no-compile``), all tracks at once, float32 by default; a full cycle
per step: interaction, three model-matched predictions and updates, mode update, combination.
Reference: FilterPy's ``IMMEstimator`` (three ``KalmanFilter``s with the same models), one object
per track, on ``--reference-tracks`` tracks (test-only dependency, imported here only). Rates are
track-steps per second, both timed in the same run: per wall-clock second (the design's
``ours_per_s``/``reference_per_s``) and per CPU second of this process (``*_per_cpu_s``), which is
what a run on an otherwise idle machine would see per core when the machine is shared.
"""

from __future__ import annotations

import argparse
import time

import torch

from torchtrack.bench._timing import best_time, report
from torchtrack.errors import TorchtrackError
from torchtrack.filters.imm_cv import ConstantVelocityIMM
from torchtrack.models import LinearPosition, ModeControlInput
from torchtrack.threads import torch_threads

NAME = "imm"
HELP = "3-model IMM, 100 000 tracks, against FilterPy's IMMEstimator per track"
DESCRIPTION = __doc__
G = 9.81
CONTROLS = [[0.0, 0.0], [0.0, 3 * G], [0.0, -G]]
TRANSITION = [[0.95, 0.05, 0.0], [0.1, 0.8, 0.1], [0.0, 0.05, 0.95]]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tracks", type=int, default=100_000, help="tracks filtered at once (default 100000)")
    parser.add_argument("--steps", type=int, default=20, help="time steps per timed pass (default 20)")
    parser.add_argument("--reference-tracks", type=int, default=100,
                        help="tracks run through FilterPy (default 100)")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: the compiled elementwise step is faster on one "
                             "thread of this 2-core machine, 6.1 M vs 3.1 M track-steps/s idle)")
    parser.add_argument("--no-compile", action="store_true", help="eager step instead of torch.compile")


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


def run(args) -> int:
    with torch_threads(args.threads):
        return _run(args)


def _run(args) -> int:
    if args.tracks < 1 or args.steps < 1 or args.reference_tracks < 1:
        raise TorchtrackError("--tracks, --steps and --reference-tracks must be >= 1")
    dtype = getattr(torch, args.dtype)
    gen = torch.Generator().manual_seed(args.seed)
    z, x0 = _data(args.tracks, args.steps, gen, dtype)
    model = _model(dtype)
    init = model.initial_state(x0, torch.diag(torch.tensor([100.0, 100.0, 25.0, 25.0], dtype=dtype)))
    compile_ok = not args.no_compile
    with torch.no_grad():
        t0 = time.perf_counter()
        model.run_packed(z[:2], init, 1.0, compile=compile_ok)       # compilation / warm-up, not timed
        warm = time.perf_counter() - t0
        seconds = best_time(lambda: model.run_packed(z, init, 1.0, compile=compile_ok), repeats=3, warmup=0)
        c0 = time.process_time()
        _, means, _ = model.run_packed(z, init, 1.0, compile=compile_ok)
        cpu = time.process_time() - c0
    ours = args.tracks * args.steps / seconds
    n_ref = min(args.reference_tracks, args.tracks)
    ref, ref_cpu, ref_x = filterpy_rate(z[:, :n_ref], x0[:n_ref], _model(torch.float64))
    deviation = float((means[-1, :n_ref].double() - ref_x).abs().max())
    workload = (f"IMM, 3 models (CV + lateral inputs 0, 3g, -g), [x, y, vx, vy], {args.tracks} tracks x "
                f"{args.steps} steps, {args.dtype}, {torch.get_num_threads()} threads, "
                f"{'torch.compile' if compile_ok else 'eager'}")
    report(workload, ours, f"filterpy IMMEstimator per track ({n_ref} tracks)", ref, "track-steps",
           args.json, extra={"ms_per_step": 1e3 * seconds / args.steps, "warmup_s": warm,
                             "ours_per_cpu_s": args.tracks * args.steps / cpu, "reference_per_cpu_s": ref_cpu,
                             "max_abs_deviation_from_reference": deviation})
    print(f"per CPU second (all threads; robust to other load): torchtrack {args.tracks * args.steps / cpu:,.0f}, "
          f"reference {ref_cpu:,.0f} track-steps")
    print(f"final combined estimates of the {n_ref} reference tracks: max |ours - FilterPy| = {deviation:.2e}")
    return 0
