"""Write a long MOTChallenge ground truth and tracker output for measuring ``torchtrack eval`` at scale.

Usage: python scripts/long_eval_sequence.py OUT_DIR [--frames 10240] [--objects 85] [--seed 0]
writes OUT_DIR/gt.txt and OUT_DIR/pred.txt: ``objects`` points moving at constant velocity, a new set of ids
every 512 frames, one object missing every tenth frame; predictions with 2 px noise and 1 % of ids switched.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, default=10240)
    parser.add_argument("--objects", type=int, default=85)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    n = args.objects
    pos, vel = rng.uniform(0, 2000, (n, 2)), rng.normal(0, 1, (n, 2))
    gt, pred = [], []
    for f in range(1, args.frames + 1):
        pos += vel
        ids = np.arange(n) + n * ((f - 1) // 512)
        keep = np.ones(n, bool)
        keep[: int(f % 10 == 0)] = False
        noisy = pos + rng.normal(0, 2, pos.shape)
        pid = np.where(rng.random(n) < 0.01, ids + 100000, ids)
        size = np.full(n, 10.0)
        gt.append(np.column_stack([np.full(n, f), ids, pos - 5, size, size])[keep])
        pred.append(np.column_stack([np.full(n, f), pid, noisy - 5, size, size])[keep])
    args.out.mkdir(parents=True, exist_ok=True)
    fmt = "%d,%d,%.2f,%.2f,%.0f,%.0f,1,-1,-1,-1"
    np.savetxt(args.out / "gt.txt", np.concatenate(gt), fmt=fmt)
    np.savetxt(args.out / "pred.txt", np.concatenate(pred), fmt=fmt)


if __name__ == "__main__":
    main()
