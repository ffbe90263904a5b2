"""Timing helpers shared by the benchmarks: best-of-k wall or CPU time, the load, the common result and its table."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import NamedTuple

from torchtrack.metrics.table import format_table


def best_time(fn: Callable[[], object], repeats: int = 3, warmup: int = 1,
              clock: Callable[[], float] = time.perf_counter) -> float:
    """Minimum seconds of ``fn()`` on ``clock`` over ``repeats`` calls after ``warmup`` calls.

    ``clock=time.process_time`` gives CPU seconds: on a shared machine the wall time counts the time the
    process waits for a core, the CPU time what the work costs (the wall time on an idle core)."""
    for _ in range(warmup):
        fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = clock()
        fn()
        best = min(best, clock() - t0)
    return best


CLOCKS = (time.perf_counter, time.process_time)
"""Wall and process CPU clocks, for a wall and a CPU timing of the same call."""


def cpu_time(fn: Callable[[], object]) -> tuple[object, float]:
    """``(fn(), process CPU seconds of that call)``."""
    c0 = time.process_time()
    out = fn()
    return out, time.process_time() - c0


def load_average() -> float | None:
    """The system's 1-minute load (``os.getloadavg``), kept in a bench's JSON as the context of its timing; None
    where the system has none."""
    try:
        return os.getloadavg()[0]
    except (OSError, AttributeError):
        return None


class BenchResult(NamedTuple):
    """One benchmark's rates: ours and the reference's, timed in the same run, in ``unit`` per second."""
    workload: str
    ours_per_s: float
    reference: str
    reference_per_s: float
    unit: str
    extra: dict   # further numbers of the JSON

    @property
    def ratio(self) -> float:
        return self.ours_per_s / self.reference_per_s if self.reference_per_s > 0 else float("inf")

    def payload(self) -> dict:
        """The design's JSON keys (``workload, ours_per_s, reference, reference_per_s, ratio, unit``), then
        ``extra``."""
        return {"workload": self.workload, "ours_per_s": self.ours_per_s, "reference": self.reference,
                "reference_per_s": self.reference_per_s, "ratio": self.ratio, "unit": self.unit, **self.extra}


def format_result(r: BenchResult) -> str:
    """The workload line, the table of both rates and the ratio."""
    rows = [["torchtrack", f"{r.ours_per_s:,.0f}"], [r.reference, f"{r.reference_per_s:,.0f}"]]
    return "\n".join([f"workload: {r.workload}", format_table(["implementation", f"{r.unit}/s"], rows),
                      f"ratio: {r.ratio:.1f}x"])

