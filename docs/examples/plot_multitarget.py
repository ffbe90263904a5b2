"""
Six multi-target trackers on the same detections
================================================

Forty targets cross a 400 × 400 px scene for 40 frames, detected with probability 0.9, position noise 1 px
and 20 false detections a frame. Every registered tracker runs on the same detections through
:func:`torchtrack.track`; the table gives the CLEAR-MOT scores from :func:`torchtrack.evaluate`.
"""

import matplotlib.pyplot as plt
import numpy as np

import torchtrack
from torchtrack.filters.trackers import tracker_names

rng = np.random.default_rng(0)
N, T, SIZE = 40, 40, 400.0
start = rng.uniform(50, SIZE - 50, (N, 2))
velocity = rng.normal(0, 2, (N, 2))
truth, detections = [], []
for frame in range(1, T + 1):
    position = start + frame * velocity
    for i, (x, y) in enumerate(position):
        truth.append([frame, i + 1, x - 4, y - 4, 8, 8, 1])
        if rng.random() < 0.9:
            zx, zy = x + rng.normal(), y + rng.normal()
            detections.append([frame, -1, zx - 4, zy - 4, 8, 8, 1])
    for zx, zy in rng.uniform(0, SIZE, (rng.poisson(20), 2)):
        detections.append([frame, -1, zx - 4, zy - 4, 8, 8, 1])
truth, detections = np.array(truth), np.array(detections)

print(f"{'tracker':>15} {'MOTA %':>7} {'IDF1 %':>7} {'IDS':>4}")
results = {}
for name in tracker_names():
    result = torchtrack.track(detections=detections, tracker=name)
    scores = torchtrack.evaluate(truth, result.tracks, threshold=5.0)
    results[name] = result
    print(f"{name:>15} {100 * scores['MOTA']:7.1f} {100 * scores['IDF1']:7.1f} {scores['IDS']:4d}")

tracks = results["gmphd"].tracks
fig, ax = plt.subplots(figsize=(5, 5))
ax.plot(detections[:, 2] + 4, detections[:, 3] + 4, ".", color="0.8", ms=2, label="detections")
for ident in np.unique(tracks[:, 1]):
    rows = tracks[tracks[:, 1] == ident]
    ax.plot(rows[:, 2] + 4, rows[:, 3] + 4, "-", lw=1)
ax.set_title("enhanced GM-PHD tracks")
ax.set_aspect("equal")
fig.tight_layout()
