"""Which truth the pipeline scores against: the paper's protocol makes the **moving** vehicles the
targets and every other vehicle a don't-care object (a track on a parked car is neither a hit nor a
false positive; ``clear_mot(..., ignore=...)``).

* synthetic sequences: the generator's ``velocity.txt`` (``frame,id,vx,vy,moving``) flags moving
  vehicles (those driving on a lane);
* WPAFB: the paper's rule, moved more than 5 px over the last 15 frames
  (:func:`torchtrack.io.wpafb.moving_mask`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from torchtrack.io.mot import MOTData
from torchtrack.io.wpafb import moving_mask, read_wpafb_csv


def parked_mask(gt: MOTData, velocity_txt: str | Path) -> np.ndarray:
    """``(K,)`` bool over ``gt``'s lines: True where ``velocity_txt`` does not flag ``(frame, id)`` as
    moving — the don't-care objects."""
    rows = np.loadtxt(velocity_txt, delimiter=",", usecols=(0, 1, 4), ndmin=2, dtype=np.int64)
    moving = rows[rows[:, 2] == 1]
    key = gt.frame * (1 << 32) + gt.id
    return ~np.isin(key, moving[:, 0] * (1 << 32) + moving[:, 1])


def wpafb_truth(csv: str | Path, frames: int) -> tuple[MOTData, np.ndarray]:
    """The WPAFB CSV's truth over its first ``frames`` frames and its don't-care mask (not moving by the
    paper's rule, computed on the whole CSV so that the history before the first frame counts)."""
    full = read_wpafb_csv(csv)
    moving = moving_mask(full)
    keep = full.frame <= frames
    return full.select(keep), ~moving[keep]
