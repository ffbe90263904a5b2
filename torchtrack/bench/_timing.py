"""Timing helpers shared by the benchmarks: best-of-k wall time and the common report."""

from __future__ import annotations

import time
from collections.abc import Callable

from torchtrack.io.outputs import write_json
from torchtrack.metrics.table import format_table


def best_time(fn: Callable[[], object], repeats: int = 3, warmup: int = 1) -> float:
    """Minimum wall-clock seconds of ``fn()`` over ``repeats`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def report(workload: str, ours_per_s: float, reference: str, reference_per_s: float, unit: str,
           json_path=None, extra: dict | None = None) -> dict:
    """Print the benchmark table and write the design's JSON keys (plus ``extra``)."""
    payload = {
        "workload": workload,
        "ours_per_s": ours_per_s,
        "reference": reference,
        "reference_per_s": reference_per_s,
        "ratio": ours_per_s / reference_per_s if reference_per_s > 0 else float("inf"),
        "unit": unit,
    }
    if extra:
        payload.update(extra)
    print(f"workload: {workload}")
    rows = [["torchtrack", f"{ours_per_s:,.0f}"], [reference, f"{reference_per_s:,.0f}"]]
    print(format_table(["implementation", f"{unit}/s"], rows))
    print(f"ratio: {payload['ratio']:.1f}x")
    write_json(json_path, payload)
    return payload
