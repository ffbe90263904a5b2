"""The truth of the WPAFB CSV as the video pipeline scores it (``track --frames/--video --truth-csv``): the
moving vehicles are the targets and every other vehicle a don't-care object (a track on a parked car is neither
a hit nor a false positive; ``clear_mot(..., ignore=...)``), moving as :func:`torchtrack.io.moving.moving_mask`
defines it for every command.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from torchtrack.io.mot import MOTData
from torchtrack.io.moving import moving_mask
from torchtrack.io.wpafb import read_wpafb_csv


def wpafb_truth(csv: str | Path, frames: int) -> tuple[MOTData, np.ndarray]:
    """The WPAFB CSV's truth over its first ``frames`` frames and its don't-care mask (not moving by the
    paper's rule, computed on the whole CSV so that the history before the first frame counts)."""
    full = read_wpafb_csv(csv)
    moving = moving_mask(full)
    keep = full.frame <= frames
    return full.select(keep), ~moving[keep]
