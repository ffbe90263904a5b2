"""Scoring the detector on the six real WPAFB AOI 02 frames (the data set that ``torchtrack data fetch wpafb``
gets, found by :func:`torchtrack.io.datasets.wpafb_folder`).

Truth: ``transformed_object_states.csv`` (``px`` = row, ``py`` = column, absent = 0, 0). A vehicle is
*moving* at frame ``k`` when it is more than 5 px from its frame-``k`` position at some frame of
``k..k+15`` (the paper's criterion looks 15 frames back; the truth starts at frame 100, so we look
forward). Frames 100 and 101 are byte-identical in the source, so the motion-based scores (velocity
error, moving vehicles) are taken on frames 102-105 only.

Two scores: *all vehicles* (every detection against every truth point; note that the truth lists
only vehicles that move at some time in the 512 frames, so detections on never-moving parked cars
count as false positives), and *moving vehicles*: detections whose predicted speed is at least
``min_speed`` px/frame against the moving truth, detections matched to non-moving truth being
don't-care.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from torchtrack.detector.evaluate import Scores, moving_only, stream
from torchtrack.errors import TorchtrackError
from torchtrack.io.datasets import WPAFB, wpafb_folder

FIRST, LAST = 100, 105


def read_truth(path: Path, first: int, last: int) -> dict[int, np.ndarray]:
    """Positions ``(n_objects, 2)`` as (x, y) px for frames ``first..last`` (NaN where absent)."""
    csv = path / "transformed_object_states.csv"
    try:
        data = np.loadtxt(csv, delimiter=",", skiprows=1)
    except (OSError, ValueError) as exc:
        raise TorchtrackError(f"{csv}: cannot read the WPAFB truth ({exc})") from exc
    rows = data[(data[:, 0] >= first) & (data[:, 0] <= last)]
    obj = rows[:, 1:].reshape(len(rows), -1, 6)
    xy = obj[..., 1::-1].copy()                                         # (column, row)
    xy[(obj[..., 0] == 0) & (obj[..., 1] == 0)] = np.nan
    return dict(zip(rows[:, 0].astype(int).tolist(), xy))


def evaluate_wpafb(detector, path: Path | None = None, radius: float = 10.0, min_speed: float = 2.0) -> dict:
    """``{"all": scores, "moving": scores}`` over frames 100-105 (see module docstring); ``path`` is the
    data set's folder (default: the located one)."""
    path = wpafb_folder() if path is None else Path(path)
    truth = read_truth(path, FIRST, LAST + 15)
    frames = []
    for k in range(FIRST, LAST + 1):
        img = cv2.imread(str(path / "frames" / f"frame_{k:06d}.png"), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise TorchtrackError(f"{path}/frames/frame_{k:06d}.png: cannot read (torchtrack data fetch "
                                  f"{WPAFB.name} gets the frames)")
        frames.append(img)
    all_s, mov_s = Scores(radius), Scores(radius)
    for k, det in zip(range(FIRST, LAST + 1), stream(detector, frames, all_s)):
        xy = truth[k]
        present = ~np.isnan(xy).any(axis=1)
        later = np.stack([truth[j] for j in range(k, k + 16) if j in truth])        # (L, n, 2)
        disp = np.nan_to_num(np.linalg.norm(later - xy[None], axis=2), nan=0.0).max(axis=0)
        moving = present & (disp > 5.0)
        vel = xy - truth[k - 1] if k - 1 in truth and k >= FIRST + 2 else None
        all_s.add(det, xy[present], None if vel is None else vel[present])
        if k >= FIRST + 2:
            mov_s.add(moving_only(det, min_speed), xy[present], vel[present], care=moving[present])
    mov_s.seconds, mov_s.cpu_seconds = all_s.seconds, all_s.cpu_seconds
    return {"all": all_s.result(), "moving": mov_s.result()}
