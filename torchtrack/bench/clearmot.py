"""``torchtrack bench clearmot``: CLEAR-MOT evaluation throughput (frames per second) against py-motmetrics.

Workload: ``--frames`` frames of ``--objects`` random-walk objects in a 400 x 400 px area, ``--objects``
predictions per frame (truth + N(0, 3^2) px noise, 5 % of them under a wrong id), centre-distance gate
10 px. Timed in the same run: :func:`torchtrack.metrics.clear_mot` (all scores, IDF1 included) and
py-motmetrics (``MOTAccumulator`` fed frame by frame with ``norm2squared_matrix``, then ``compute`` of the
MOTChallenge metrics) when it is installed; both give the same counts (checked here too).
"""

from __future__ import annotations

import warnings

import numpy as np

from torchtrack.bench._timing import BenchResult, best_time
from torchtrack.io.mot import MOTData, from_points
from torchtrack.metrics import clear_mot


def workload(frames: int, objects: int, seed: int) -> tuple[MOTData, MOTData]:
    rng = np.random.default_rng(seed)
    fr = np.repeat(np.arange(1, frames + 1), objects)
    ids = np.tile(np.arange(objects), frames)
    pos = (rng.uniform(0, 400, (objects, 2)) + np.cumsum(rng.normal(0, 1, (frames, objects, 2)), 0)).reshape(-1, 2)
    gt = from_points(fr, ids, pos[:, 0], pos[:, 1])
    pid = np.where(rng.random(ids.size) < 0.05, ids + objects, ids)
    noisy = pos + rng.normal(0, 3, pos.shape)
    return gt, from_points(fr, pid, noisy[:, 0], noisy[:, 1])


def _motmetrics(gt: MOTData, pred: MOTData, threshold: float) -> dict:
    import motmetrics as mm

    acc = mm.MOTAccumulator()
    g_split, p_split = gt.split(), pred.split(gt.frames())
    gc, pc = gt.centers(), pred.centers()
    for f, gi, pi in zip(gt.frames(), g_split, p_split):
        d = np.sqrt(mm.distances.norm2squared_matrix(gc[gi], pc[pi], max_d2=threshold**2))
        acc.update(gt.id[gi], pred.id[pi], d, frameid=int(f))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mm.metrics.create().compute(acc, metrics=mm.metrics.motchallenge_metrics, return_dataframe=False)


def measure(frames: int = 512, objects: int = 100, repeats: int = 3, seed: int = 0) -> BenchResult:
    """Time :func:`~torchtrack.metrics.clear_mot` (best of ``repeats``) and py-motmetrics, when installed, on
    :func:`workload`; ``extra`` says whether their counts agree (None: no reference)."""
    gt, pred = workload(frames, objects, seed)
    ours = best_time(lambda: clear_mot(gt, pred, threshold=10.0), repeats=repeats)
    scores = clear_mot(gt, pred, threshold=10.0)
    try:
        import motmetrics  # noqa: F401  (test-only dependency, optional here)
    except ImportError:
        ref_time, agree = float("nan"), None
    else:
        ref_time = best_time(lambda: _motmetrics(gt, pred, 10.0), repeats=1, warmup=0)
        ref = _motmetrics(gt, pred, 10.0)
        agree = all(scores[k] == int(ref[r]) for k, r in (("IDS", "num_switches"), ("FP", "num_false_positives"),
                                                          ("FN", "num_misses"), ("FRAG", "num_fragmentations")))
    return BenchResult(f"CLEAR-MOT + IDF1, {frames} frames x {objects} objects x {objects} predictions",
                       frames / ours, "py-motmetrics", frames / ref_time if ref_time == ref_time else 0.0, "frames",
                       {"seconds": ours, "reference_seconds": ref_time, "counts_agree": agree,
                        "MOTA": scores["MOTA"], "IDS": scores["IDS"]})
