"""Grid search over the same parameters, the baseline that gradient tuning is compared with.

Every combination of the listed constrained values is set on a fresh copy of the start filter and
scored by the tunable's :meth:`~torchtrack.tuning.registry.Tunable.evaluate` on the *training* items
(e.g. MOTA of the streaming tracker); the best combination is then scored on the held-out items.
Each combination costs one forward pass over the training items (no gradient).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Mapping
from typing import Any

from torch import nn

from torchtrack.errors import TorchtrackError
from torchtrack.tuning.parameters import checked_parameters, set_values
from torchtrack.tuning.registry import Tunable, TuneData, check_keys, search_scores

GRID_KEYS = ("values", "metric", "maximize")


def grid_search(tunable: Tunable, module: nn.Module, config: Mapping[str, Any], data: TuneData,
                progress: bool = True) -> dict[str, Any]:
    """Run the grid of ``config`` (``values: {name: [v, …]}``, ``metric`` (default ``MOTA``),
    ``maximize`` (default true)); returns the best values, its training and held-out metrics, the
    number of combinations and item evaluations, and the seconds spent."""
    check_keys(config, GRID_KEYS, "grid")
    values = config.get("values") or {}
    if not values:
        raise TorchtrackError("grid.values must map parameter names to lists of values")
    checked_parameters(module, values, "parameter(s)", "grid: ")
    metric = str(config.get("metric", "MOTA"))
    sign = 1.0 if config.get("maximize", True) else -1.0
    names = list(values)
    combos = list(itertools.product(*(list(values[n]) for n in names)))
    from tqdm import tqdm

    best: tuple[float, dict | None, dict] = (-math.inf, None, {})
    t0 = time.perf_counter()
    for combo in tqdm(combos, desc="grid", disable=not progress, leave=False):
        point = dict(zip(names, combo))
        set_values(module, point)
        scores = search_scores(tunable, module, data.train, metric, "grid.metric")
        if math.isfinite(scores[metric]) and sign * scores[metric] > best[0]:
            best = (sign * scores[metric], point, scores)
    seconds = time.perf_counter() - t0
    if best[1] is None:
        raise TorchtrackError(f"grid: no combination gave a finite {metric}")
    set_values(module, best[1])
    held = tunable.evaluate(module, data.held_out) if data.held_out else {}
    return {"best": {n: float(v) for n, v in best[1].items()}, "metric": metric, "train": best[2],
            "held_out": held, "combinations": len(combos), "filter_evaluations": len(combos) * len(data.train),
            "frames": len(combos) * sum(tunable.item_frames(i) for i in data.train),
            "training_passes": len(combos) * len(data.train) / max(len(data.train), 1), "seconds": seconds,
            "derived": tunable.derived(module)}
