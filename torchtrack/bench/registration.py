"""``torchtrack bench registration``: frame registration speed and accuracy on synthetic sequences.

Workload: ``--sequences`` synthetic sequences (``torchtrack.sim.video`` defaults, ``--size`` px square,
``--frames`` frames each, seeds of the detector's held-out test split) with their true camera motion.
Timed in the same run on the same frames: ours (:class:`torchtrack.pipeline.registration.Registration`,
keyframe corners + Lucas–Kanade + RANSAC) and the reference, OpenCV's classic feature pipeline (ORB
features, brute-force Hamming matching, RANSAC homography — ``method="orb"``). Also reported: the error
of each against the true camera motion (median over frames of the median transfer error on a 16 px grid)
and of ours with ECC refinement.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from torchtrack.bench._timing import BenchResult, format_result
from torchtrack.detector.dataset import split_seed
from torchtrack.geometry import transfer_error
from torchtrack.pipeline.registration import Registration, RegistrationConfig
from torchtrack.sim.video import VideoConfig, generate_sequence


def evaluate(config: RegistrationConfig, sequences: list[list]) -> tuple[float, np.ndarray]:
    """Frames per second of ``Registration(config)`` over ``sequences`` (lists of ``VideoFrame``) and the
    per-frame median transfer errors (px) against the truth, first frames excluded."""
    errors, seconds, frames = [], 0.0, 0
    for seq in sequences:
        reg = Registration(config)
        h1 = seq[0].homography
        for f in seq:
            t0 = time.perf_counter()
            est = reg(f.image).homography
            seconds += time.perf_counter() - t0
            frames += 1
            if f.index:
                errors.append(np.median(transfer_error(est, h1 @ np.linalg.inv(f.homography), f.image.shape)))
    return frames / seconds, np.asarray(errors)


def _stats(e: np.ndarray) -> dict:
    return {"median_px": float(np.median(e)), "p90_px": float(np.percentile(e, 90)), "max_px": float(e.max())}


def measure(sequences: int = 3, frames: int = 30, size: int = 512, seed: int = 0) -> BenchResult:
    """Time and score ours, OpenCV's ORB + RANSAC and ours with ECC on ``sequences`` synthetic sequences of
    ``frames`` ``size`` x ``size`` frames (the held-out split's seeds)."""
    cfg = VideoConfig(height=size, width=size, frames=frames)
    seqs = [list(generate_sequence(cfg, torch.Generator().manual_seed(split_seed(seed, "test", i))))
            for i in range(sequences)]
    ours_fps, ours_err = evaluate(RegistrationConfig(), seqs)
    ref_fps, ref_err = evaluate(RegistrationConfig(method="orb", features=1500), seqs)
    ecc_fps, ecc_err = evaluate(RegistrationConfig(ecc=True), seqs)
    extra = {"error": {"ours_lk": _stats(ours_err), "reference_orb": _stats(ref_err), "ours_lk_ecc": _stats(ecc_err)},
             "ours_lk_ecc_per_s": ecc_fps, "frames": int(len(ours_err) + len(seqs)), "size": size}
    return BenchResult(f"registration of {sequences} x {frames} synthetic {size}x{size} frames",
                       ours_fps, "OpenCV ORB + RANSAC", ref_fps, "frames", extra)


def format_report(r: BenchResult) -> str:
    """The table, each method's error against the true camera motion and the rate with ECC."""
    lines = [format_result(r)]
    for name, s in r.extra["error"].items():
        lines.append(f"error vs true camera motion, {name}: median {s['median_px']:.3f} px, p90 {s['p90_px']:.3f}, "
                     f"max {s['max_px']:.3f}")
    lines.append(f"ours + ECC refinement: {r.extra['ours_lk_ecc_per_s']:.1f} frames/s")
    return "\n".join(lines)
