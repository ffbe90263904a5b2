"""The one scoring call and the one Table 1 printer of every command that runs a tracker.

:func:`score` is CLEAR-MOT and IDF1 (:func:`torchtrack.metrics.clear_mot`) and HOTA
(:func:`torchtrack.metrics.hota`, centre similarity at the same threshold) with plain floats;
:func:`format_table1` prints tracker → scores in the layout of Table 1 of Aguilar et al. (ICASSP 2023): GT
trajectories, MT/PT/ML as % of them, FP, FN, IDS, MOTA %, MOTP (mean matched centre distance, px) and the
tracker's frames per second, with HOTA % and IDF1 % added beside MOTA. Every table opens with the line that
names how it was scored (:func:`protocol`): the moving vehicles (the default of every command that tracks and
scores, as ``eval --moving``) or all objects, and the gate.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from torchtrack.io.mot import MOTData
from torchtrack.metrics.clear_mot import clear_mot
from torchtrack.metrics.hota import KEYS as HOTA_KEYS
from torchtrack.metrics.hota import hota

TABLE1_HEADER = ["Method", "GT", "MT (%)", "PT (%)", "ML (%)", "FP", "FN", "IDS", "MOTA (%)", "HOTA (%)",
                 "IDF1 (%)", "MOTP (px)", "FPS"]


PROTOCOLS = {True: "moving vehicles (the others don't-care)", False: "all objects"}
"""The scoring protocols as the tables name them: ``moving_only`` → the objects that are targets."""


def gate(threshold: float, iou: float | None = None) -> str:
    """How a prediction matches an object (``eval --json``'s ``gate``): a centre distance or an IoU."""
    return f"IoU >= {iou}" if iou is not None else f"centre distance <= {threshold} px"


def scoring(moving_only: bool, threshold: float, iou: float | None = None) -> dict:
    """The keys of ``eval --json`` that say how tracks were scored: ``gate`` and ``moving_only``."""
    return {"gate": gate(threshold, iou), "moving_only": bool(moving_only)}


def protocol(moving_only: bool, threshold: float, iou: float | None = None) -> str:
    """The line above a scores table: the objects that are targets (:data:`PROTOCOLS`) and the :func:`gate`."""
    return f"scored on {PROTOCOLS[bool(moving_only)]}, {gate(threshold, iou)}"


def score(gt: MOTData, tracks: MOTData, threshold: float = 10.0, ignore: np.ndarray | None = None) -> dict:
    """CLEAR-MOT and IDF1 of ``tracks`` against ``gt`` at a centre distance of ``threshold`` px, and the HOTA
    keys (``HOTA, DetA, AssA, LocA, DetRe, DetPr, AssRe, AssPr``, fractions) with the centre similarity
    ``max(0, 1 - d / threshold)``; ``ignore (K,)`` marks don't-care truth lines (e.g. parked vehicles under
    the paper's moving-objects protocol), removed with the predictions on them before either is scored. The tracks
    are scored as their MOTChallenge file holds them (:meth:`MOTData.as_written`): a command's printed scores are
    those ``torchtrack eval`` gives on the files it wrote."""
    tracks = tracks.as_written()
    scores = clear_mot(gt, tracks, threshold=threshold, ignore=ignore)
    found = hota(gt, tracks, threshold=threshold, ignore=ignore)
    scores.update({k: found[k] for k in HOTA_KEYS})
    return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in scores.items()}


def table1_row(name: str, m: Mapping) -> list:
    """One row of Table 1 from a :func:`score` dict with ``FPS`` (MT/PT/ML as % of GT; 0 where GT is 0)."""
    gt = max(int(m["GT"]), 1)
    return [name, int(m["GT"]), 100 * m["MT"] / gt, 100 * m["PT"] / gt, 100 * m["ML"] / gt, int(m["FP"]),
            int(m["FN"]), int(m["IDS"]), 100 * m["MOTA"], 100 * m["HOTA"], 100 * m["IDF1"], m["MOTP"], m["FPS"]]


def format_table1(scores: Mapping[str, Mapping], title: str) -> str:
    """Table 1 with one row per tracker of ``scores`` (tracker name → :func:`score` dict with ``FPS``), under
    ``title``: the line naming how it was scored (:func:`protocol`)."""
    rows = [table1_row(name, m) for name, m in scores.items()]
    return f"{title}\n{format_table(TABLE1_HEADER, rows, floatfmt='.2f')}"


def format_table(header: Sequence[str], rows: Sequence[Sequence], floatfmt: str = ".3f") -> str:
    """A plain text table, columns right-aligned; floats formatted with ``floatfmt``."""
    def cell(v):
        if isinstance(v, float):
            return format(v, floatfmt)
        return str(v)

    cells = [[cell(v) for v in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(header)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(header, widths))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)
