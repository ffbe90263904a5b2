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

from torchtrack.bench._timing import report
from torchtrack.detector.dataset import split_seed
from torchtrack.geometry import transfer_error
from torchtrack.pipeline.registration import Registration, RegistrationConfig
from torchtrack.sim.video import VideoConfig, generate_sequence

NAME = "registration"
HELP = "registration frames/s and error vs the true camera motion (ours LK vs OpenCV ORB+RANSAC)"
DESCRIPTION = __doc__


def add_arguments(parser) -> None:
    parser.add_argument("--sequences", type=int, default=3, help="synthetic sequences (default 3)")
    parser.add_argument("--frames", type=int, default=30, help="frames per sequence (default 30)")
    parser.add_argument("--size", type=int, default=512, help="frame side in px (default 512)")


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


def run(args) -> int:
    cfg = VideoConfig(height=args.size, width=args.size, frames=args.frames)
    seqs = [list(generate_sequence(cfg, torch.Generator().manual_seed(split_seed(args.seed, "test", i))))
            for i in range(args.sequences)]
    ours_fps, ours_err = evaluate(RegistrationConfig(), seqs)
    ref_fps, ref_err = evaluate(RegistrationConfig(method="orb", features=1500), seqs)
    ecc_fps, ecc_err = evaluate(RegistrationConfig(ecc=True), seqs)

    def stats(e: np.ndarray) -> dict:
        return {"median_px": float(np.median(e)), "p90_px": float(np.percentile(e, 90)), "max_px": float(e.max())}

    extra = {"error": {"ours_lk": stats(ours_err), "reference_orb": stats(ref_err), "ours_lk_ecc": stats(ecc_err)},
             "ours_lk_ecc_per_s": ecc_fps, "frames": int(len(ours_err) + len(seqs)), "size": args.size}
    report(f"registration of {args.sequences} x {args.frames} synthetic {args.size}x{args.size} frames",
           ours_fps, "OpenCV ORB + RANSAC", ref_fps, "frames", args.json, extra)
    for name, e in extra["error"].items():
        s = stats(e) if isinstance(e, np.ndarray) else e
        print(f"error vs true camera motion, {name}: median {s['median_px']:.3f} px, p90 {s['p90_px']:.3f}, "
              f"max {s['max_px']:.3f}")
    print(f"ours + ECC refinement: {ecc_fps:.1f} frames/s")
    return 0
