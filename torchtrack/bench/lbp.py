"""``torchtrack bench lbp``: loopy belief propagation marginals on n × n association problems.

Ours: :func:`torchtrack.association.lbp.lbp_marginals` in fixed-iteration mode. Reference: the same
Williams & Lau (2014) iteration written in NumPy (the same vectorised "total minus own" passes),
timed in the same run on the same problems. Throughput is problems per second at the largest size;
per-size times in milliseconds are reported beside it.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import torch

from torchtrack.association.lbp import LOG_NEW_FLOOR, lbp_marginals
from torchtrack.bench._timing import CLOCKS, BenchResult, best_time, format_result, load_average
from torchtrack.metrics.table import format_table
from torchtrack.threads import TRACKER_THREADS, torch_threads


def _np_sum_of_others(v: np.ndarray, floor, axis: int) -> tuple[np.ndarray, np.ndarray]:
    total = v.sum(axis, keepdims=True) + floor
    dominant = v > 0.5 * total
    rest = np.where(dominant, 0.0, v).sum(axis, keepdims=True) + floor
    return np.where(dominant, rest, total - v), total


def numpy_lbp(log_w: np.ndarray, log_miss: np.ndarray, log_new: np.ndarray, iterations: int,
              tol: float | None = None):
    """The reference: Williams & Lau (2014) message passing in NumPy, same per-track scaling, passes and
    stopping rule (largest change of a miss or new-target marginal below ``tol``, checked every second
    iteration)."""
    torch_dtype = torch.float32 if log_w.dtype == np.float32 else torch.float64
    lr = log_w - np.maximum(log_new, LOG_NEW_FLOOR[torch_dtype])[None, :]
    log_c = np.maximum(log_miss, lr.max(-1, initial=-np.inf))
    finite = np.isfinite(log_c)
    log_c = np.where(finite, log_c, 0.0)
    a = np.exp(lr - log_c[:, None])
    a0 = np.exp(np.where(finite, log_miss - log_c, 0.0))[:, None]
    tiny = np.finfo(a.dtype).tiny
    prod = a
    last = None
    for it in range(1, iterations + 1):
        others, total = _np_sum_of_others(prod, a0, -1)
        mu = a / np.maximum(others, tiny)
        others, col = _np_sum_of_others(mu, 1.0, -2)
        prod = a / others
        if tol is not None and (it % 2 == 0 or it == iterations):
            stat = np.concatenate([(a0 / total).ravel(), 1.0 / col.ravel()])
            if last is not None and (stat.size == 0 or np.abs(stat - last).max() < tol):
                break
            last = stat
    total = prod.sum(-1, keepdims=True) + a0
    return prod / total, (a0 / total)[:, 0]


def make_problem(n: int, density: float, gen: torch.Generator, dtype: torch.dtype):
    log_w = torch.randn(n, n, generator=gen, dtype=torch.float64) * 2.0 - 1.0
    log_w[torch.rand(n, n, generator=gen) > density] = float("-inf")
    log_miss = torch.randn(n, generator=gen, dtype=torch.float64) * 0.5
    log_new = torch.randn(n, generator=gen, dtype=torch.float64) * 0.5 - 1.0
    return log_w.to(dtype), log_miss.to(dtype), log_new.to(dtype)


def measure(sizes: list[int], iterations: int = 15, density: float = 0.2, dtype: str = "float32",
            threads: int = TRACKER_THREADS, repeats: int = 5, seed: int = 0) -> BenchResult:
    """Time ours and the NumPy reference (best of ``repeats``, on ``threads`` torch threads) on one random
    ``n x n`` problem per ``sizes`` entry (``density``: the gated fraction), ``iterations`` fixed; the rates are
    the last size's, every size's times and largest marginal difference are ``extra["per_size"]``."""
    with torch_threads(threads):
        torch_dtype = getattr(torch, dtype)
        gen = torch.Generator().manual_seed(seed)
        per_size = {}
        for n in sizes:
            lw, lm, ln = make_problem(n, density, gen, torch_dtype)
            run_ours = partial(lbp_marginals, lw, lm, ln, iterations=iterations, tol=None, check=False)
            run_ref = partial(numpy_lbp, lw.numpy(), lm.numpy(), ln.numpy(), iterations)
            with torch.no_grad():
                ours, ours_cpu = (best_time(run_ours, repeats, clock=clock) for clock in CLOCKS)
            ref, ref_cpu = (best_time(run_ref, repeats, clock=clock) for clock in CLOCKS)
            a_ours = lbp_marginals(lw, lm, ln, iterations=iterations, tol=None).assoc.numpy()
            a_ref, _ = run_ref()
            per_size[n] = {"ours_ms": ours * 1e3, "numpy_ms": ref * 1e3, "ours_cpu_ms": ours_cpu * 1e3,
                           "numpy_cpu_ms": ref_cpu * 1e3, "max_abs_diff": float(np.abs(a_ours - a_ref).max())}
        n = sizes[-1]
        return BenchResult(f"LBP marginals, {n}x{n}, {iterations} iterations, {dtype}, gate density {density}",
                           1 / ours, "numpy (same algorithm)", 1 / ref, "problems",
                           {"per_size": per_size, "threads": torch.get_num_threads(), "load_average": load_average()})


def format_report(r: BenchResult) -> str:
    """The per-size times and differences, then the table of the largest size's rates."""
    rows = [[f"{n}x{n}", s["ours_ms"], s["numpy_ms"], s["ours_cpu_ms"], s["numpy_cpu_ms"], f"{s['max_abs_diff']:.1e}"]
            for n, s in r.extra["per_size"].items()]
    return "\n".join([format_table(["problem", "torchtrack ms", "numpy ms", "torchtrack cpu ms", "numpy cpu ms",
                                     "max |diff|"], rows), format_result(r)])
