"""The registration's per-frame record of a pipeline run: ``registration.csv`` and its summary in ``metrics.json``.

Columns: ``frame``, ``residual_px`` (frame-to-frame residual, :mod:`torchtrack.pipeline.registration`; empty on
a segment's first frame), ``inliers``, ``search`` (``first``, ``predicted``, ``phase``, ``orb``, ``none``),
``segment``, ``gate_pass`` (the fraction of the frame's pixels the moving-object gate passes,
:func:`torchtrack.pipeline.detection.gate_pass_fraction`; empty without a previous frame).
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np

from torchtrack.pipeline.registration import RegistrationResult


def _cell(value: float) -> str:
    return "" if math.isnan(value) else f"{value:.4f}"


def _stats(values: list[float]) -> dict | None:
    finite = [v for v in values if not math.isnan(v)]
    if not finite:
        return None
    return {"median": float(np.median(finite)), "p90": float(np.percentile(finite, 90)), "max": float(max(finite)),
            "frames": len(finite)}


class RegistrationLog:
    """Appends one line per frame to ``path`` (flushed, a context manager) and keeps the values for
    :meth:`summary`."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.residuals: list[float] = []
        self.gate: list[float] = []
        self.searches: Counter = Counter()
        self.segments = 0

    def __enter__(self) -> RegistrationLog:
        self._file = self.path.open("w")
        self._file.write("frame,residual_px,inliers,search,segment,gate_pass\n")
        return self

    def __exit__(self, *exc) -> None:
        self._file.close()

    def add(self, index: int, result: RegistrationResult, gate_pass: float) -> None:
        """Frame ``index``'s registration ``result`` and the fraction of its pixels the gate passes."""
        self.residuals.append(result.residual)
        self.gate.append(gate_pass)
        self.searches[result.search] += 1
        self.segments = max(self.segments, result.segment + 1)
        self._file.write(f"{index},{_cell(result.residual)},{result.inliers},{result.search},{result.segment},"
                         f"{_cell(gate_pass)}\n")
        self._file.flush()

    def summary(self) -> dict:
        """Residual and gate statistics (``None`` where never measured), segments and searches."""
        return {"residual_px": _stats(self.residuals), "gate_pass_fraction": _stats(self.gate),
                "segments": self.segments, "searches": dict(self.searches)}
