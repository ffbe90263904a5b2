"""Which vehicles are *moving*: the one definition behind ``torchtrack eval --moving``, ``track --sequences``,
``torchtrack demo``, ``track --truth-csv`` and the WPAFB benchmark (:func:`moving_mask`).

The paper's protocol (Aguilar, Ortner & Zerubia 2023, Sec. 3.1) scores the vehicles that drive and makes every
other vehicle a don't-care object: a prediction on a parked car is neither a hit nor a false positive. A truth
line is **moving** when

* the truth carries the simulator's flag — a synthetic sequence's ``velocity.txt`` beside its ``gt.txt``
  (``frame,id,vx,vy,moving``, written by :func:`torchtrack.sim.video.write_sequence`; ``moving`` is 1 for a
  vehicle driving on a lane, 0 for a parked one) — and the flag is 1;
* otherwise (real truth: WPAFB, any ``gt.txt`` alone), by the paper's rule: the object moved more than 5 px
  over the last 15 frames (:func:`displacement_rule`), which estimates the same flag from positions on
  stabilised frames.

Why the flag wins where it exists: the rule reads positions in the frame's own coordinates, and the synthetic
camera jitters (about 1 px of translation and 0.2 % of rotation and scale per frame, independently), so on the
demo's sequence the rule calls 21 parked vehicles moving on 36 lines and, as it must, misses the first frame
of every driving vehicle (60 lines): 75 objects instead of the 55 that drive. The flag is the simulator's own
truth; the rule is what one can compute where there is none. Both go through :func:`moving_mask`, and
``eval --moving`` reads the ``velocity.txt`` beside its ``--gt`` (:func:`flags_beside`), so scoring a
sequence's tracks with ``eval --moving`` gives the same figures as the command that tracked it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import MOTData

MOVING_DISPLACEMENT = 5.0
"""Pixels an object must have moved over :data:`MOVING_WINDOW` frames to count as moving (the paper's rule)."""
MOVING_WINDOW = 15
FLAGS_FILE = "velocity.txt"
"""The simulator's per-line motion file, in a synthetic sequence's folder beside ``gt.txt``."""


def displacement_rule(truth: MOTData, min_displacement: float = MOVING_DISPLACEMENT,
                      window: int = MOVING_WINDOW) -> np.ndarray:
    """(K,) bool: the object of each line moved more than ``min_displacement`` px over the last ``window`` frames.

    The displacement of object ``i`` at frame ``k`` is ``||p_i(k) - p_i(k0)||`` with ``k0`` the earliest frame
    of ``i`` in ``[k - window, k]`` (the object's first frame when it is younger than the window), so an
    object is never moving on its first frame. This is the paper's selection of "objects that moved more
    than 5 pixels during the last 15 frames" (Aguilar et al. 2023, Sec. 3.1). Lines in ``truth``'s order.
    """
    order = np.lexsort((truth.frame, truth.id))
    ids, frames = truth.id[order], truth.frame[order]
    centres = truth.centers()[order]
    span = int(frames.max() - frames.min()) + window + 2 if frames.size else 1
    key = (ids - ids.min() if ids.size else ids) * span + (frames - (frames.min() if frames.size else 0))
    start = np.searchsorted(key, key - window, side="left")  # same id: frames are within one span block
    moved = np.linalg.norm(centres - centres[start], axis=1) > min_displacement
    out = np.empty(truth.size, dtype=bool)
    out[order] = moved
    return out


def flagged_moving(truth: MOTData, flags: str | os.PathLike) -> np.ndarray:
    """(K,) bool over ``truth``'s lines: True where the simulator's ``flags`` file (``frame,id,vx,vy,moving``)
    flags ``(frame, id)`` as moving; a line the file does not list is not moving."""
    try:
        rows = np.loadtxt(flags, delimiter=",", usecols=(0, 1, 4), ndmin=2, dtype=np.int64)
    except (OSError, ValueError, IndexError) as exc:
        raise TorchtrackError(f"{flags}: not a velocity.txt of simulate-video (frame,id,vx,vy,moving): {exc}"
                              ) from None
    moving = rows[rows[:, 2] == 1]
    return np.isin(truth.frame * (1 << 32) + truth.id, moving[:, 0] * (1 << 32) + moving[:, 1])


def flags_beside(gt_path: str | os.PathLike) -> Path | None:
    """The ``velocity.txt`` of the sequence whose truth is ``gt_path`` (``S/gt.txt`` or ``S/gt/gt.txt``:
    ``S/velocity.txt``), or None where there is none."""
    folder = Path(gt_path).parent
    if folder.name == "gt" and not (folder / FLAGS_FILE).is_file():
        folder = folder.parent
    found = folder / FLAGS_FILE
    return found if found.is_file() else None


def moving_mask(truth: MOTData, flags: str | os.PathLike | None = None,
                min_displacement: float = MOVING_DISPLACEMENT, window: int = MOVING_WINDOW) -> np.ndarray:
    """(K,) bool over ``truth``'s lines: the moving vehicles (module docstring) — the simulator's ``flags``
    file where given, else the paper's rule (:func:`displacement_rule` with ``min_displacement`` px over
    ``window`` frames). The other lines are the don't-care objects of the paper's protocol."""
    if flags is not None:
        return flagged_moving(truth, flags)
    return displacement_rule(truth, min_displacement, window)


SCORES = ("moving", "all")
"""The scoring protocols of every command that tracks and scores: ``moving`` (the default, the paper's: the
moving vehicles are the targets, the others don't-care) or ``all`` (every object is a target)."""


def dont_care(truth: MOTData, score: str = "moving", flags: str | os.PathLike | None = None) -> np.ndarray | None:
    """(K,) bool over ``truth``'s lines: the don't-care objects under the protocol ``score`` (:data:`SCORES`) —
    for ``moving`` the lines that are not moving (:func:`moving_mask` with ``flags``), as ``eval --moving``
    scores; for ``all`` None (every line is a target)."""
    if score not in SCORES:
        raise TorchtrackError(f"score must be one of {', '.join(SCORES)}; got {score!r}")
    return ~moving_mask(truth, flags) if score == "moving" else None
