"""A short line search on a task metric (e.g. MOTA) after the gradient fit, on the training items only.

The gradient losses — a likelihood, a soft GOSPA — are not the task metric: MOTA also depends on the
tracker's discrete logic (extraction at ``w > ½``, label confirmation, coasting), which no gradient
sees, so the likelihood's optimum (the best *model* of the data) need not be the best MOTA. This stage
starts at the fitted values and moves each listed parameter along the optimiser's scaled variable
``u`` (``raw = raw_fit + s·u``, :func:`~torchtrack.tuning.trainer.step_scale`: a step ``δ`` is about a
relative change ``δ`` of a positive parameter, a change ``δ`` of a probability's logit): it steps
``+δ`` and keeps stepping while the training metric improves, otherwise tries ``−δ`` the same way, then
goes on to the next parameter; after a sweep over all of them ``δ`` halves. With ``lookahead`` (the
default) a first step that does not improve is followed by one of ``2δ`` before the direction is given
up: MOTA is flat in places along a parameter (it changes only when a track's fate changes), and a search
that stops at the first flat step can stay where the gradient fit left it. A vector or matrix
parameter moves all its entries together. Every metric evaluation is one forward pass over all
training items (counted in the report); held-out items are never used.

The training metric is noisy at the scale of the last steps (a few ground-truth boxes in ten
thousand decide between neighbouring points), so the single best point is partly chosen by the
noise of this one data set. With ``average: k`` the result is instead the centroid, in ``u``, of
the ``k`` distinct points with the highest training metric (a smoothed argmax: the middle of the
good region),

    u* = (1/k) Σ_{i ∈ top k} u_i,

scored once more on the training items (that evaluation is counted within the budget).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

from torch import Tensor, nn

from torchtrack.config import from_mapping
from torchtrack.errors import TorchtrackError
from torchtrack.tuning.config import RefineOptions
from torchtrack.tuning.parameters import checked_parameters, get_values, plain, set_raw
from torchtrack.tuning.registry import Tunable, TuneData, search_scores
from torchtrack.tuning.trainer import step_scale


def refine(tunable: Tunable, module: nn.Module, config: Mapping[str, Any], data: TuneData,
           trainable: Sequence[str], progress: bool = True) -> dict[str, Any]:
    """Line search of ``config`` (``metric`` (default ``MOTA``), ``maximize`` (default true),
    ``parameters`` (default: the trainable ones), ``step`` δ (default 0.5), ``sweeps`` (default 2),
    ``evaluations`` (the budget of metric evaluations, default 12), ``average`` k (default 1: the best
    point; k > 1: the centroid of the k best points, see above)) from ``module``'s current values,
    which it leaves at the chosen point. Returns the training metric at the start, the best one
    searched and the one at the chosen point (``final``), the values, the number of metric
    evaluations, items and frames filtered, and the seconds spent. ``lookahead`` (default true): a first
    step of ``δ`` in a direction that does not improve is followed by one of ``2δ`` (see above)."""
    options = from_mapping(RefineOptions, config, "tune config", "refine")
    metric, sign = options.metric, 1.0 if options.maximize else -1.0
    names = list(options.parameters or trainable)
    params = checked_parameters(module, names, "parameter(s)", "refine: ")
    delta, budget, average = options.step, options.evaluations, options.average
    if not data.train:
        raise TorchtrackError("the training set is empty: refine has nothing to score")
    base: dict[str, Tensor] = {n: params[n].raw.detach().clone() for n in names}
    scale: dict[str, Tensor] = {n: step_scale(params[n]) for n in names}
    t0 = time.perf_counter()
    evaluations = 0
    seen: dict[str, tuple[float, dict[str, float], dict]] = {}   # key -> (signed metric, point, all scores)
    from tqdm import tqdm

    bar = tqdm(total=budget, desc=f"refine {metric}", disable=not progress, leave=False)

    def score(point: Mapping[str, float]) -> float:
        nonlocal evaluations
        set_raw(module, {n: base[n] + scale[n] * point[n] for n in names})
        scores = search_scores(tunable, module, data.train, metric, "refine.metric")
        evaluations += 1
        bar.update(1)
        value = sign * float(scores[metric])
        value = value if math.isfinite(value) else -math.inf
        seen[_key(point)] = (value, dict(point), scores)
        return value

    search_budget = budget - (average > 1)      # keep one evaluation for the centroid
    u = {n: 0.0 for n in names}
    start = best = score(u)
    for _ in range(options.sweeps):
        for n in names:
            for direction in (1.0, -1.0):
                moved = False
                while evaluations < search_budget:
                    trial = {**u, n: u[n] + direction * delta}
                    value = score(trial)
                    if value <= best and options.lookahead and not moved and evaluations < search_budget:
                        trial = {**u, n: u[n] + 2 * direction * delta}
                        value = score(trial)
                    if value > best:
                        u, best, moved = trial, value, True
                    else:
                        break
                if moved or evaluations >= search_budget:
                    break
        delta /= 2
    final = best
    if average > 1:
        top = [r[1] for r in sorted(seen.values(), key=lambda r: -r[0]) if r[0] > -math.inf][:average] or [u]
        u = {n: sum(p[n] for p in top) / len(top) for n in names}
        final = seen[_key(u)][0] if _key(u) in seen else score(u)
    bar.close()
    set_raw(module, {n: base[n] + scale[n] * u[n] for n in names})
    train_frames = sum(tunable.item_frames(i) for i in data.train)
    return {"metric": metric, "parameters": names, "start": sign * start, "best": sign * best,
            "final": sign * final, "average": average, "train": seen[_key(u)][2], "moved": dict(u),
            "values": plain(get_values(module, names)),
            "metric_evaluations": evaluations, "filter_evaluations": evaluations * len(data.train),
            "frames": evaluations * train_frames, "seconds": time.perf_counter() - t0}


def _key(point: Mapping[str, float]) -> str:
    return ",".join(f"{v:.12g}" for v in point.values())
