"""``torchtrack bench hota``: HOTA throughput against TrackEval's ``HOTA`` metric class, timed in the same run.

Workload: a tracker output and its ground truth, by default the size of the WPAFB benchmark's (``--frames``
512 frames of ``--objects`` 85 random-walk objects, about 43,500 truth points, one prediction each with
N(0, 3^2) px noise and 5 % of them under a wrong id); ``--gt``/``--pred`` score given MOTChallenge files
instead, e.g. the output of ``torchtrack track --benchmark wpafb``. Centre similarity, D = 10 px.

Timed: :func:`torchtrack.metrics.hota` from the two tables (its similarities included) against TrackEval 1.3's
``HOTA().eval_sequence`` on data prepared beforehand — TrackEval has no dataset class for points, so its
metric class on the per-frame ids and similarity matrices is the fair reference; preparing those in NumPy
(:func:`trackeval_data`) is timed apart and not charged to it. Both give the same scores (checked here, to
1e-9). TrackEval is a test-only dependency (``pip install torchtrack[test]``); without it only torchtrack's
time is reported.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from torchtrack.bench._timing import BenchResult, best_time
from torchtrack.bench.clearmot import workload
from torchtrack.io.mot import MOTData
from torchtrack.metrics import hota
from torchtrack.metrics.hota import KEYS


def trackeval_data(gt: MOTData, pred: MOTData, threshold: float = 10.0, iou: float | None = None) -> dict:
    """TrackEval's per-sequence data dict for its metric classes: ids relabelled 0.., every frame from the
    first to the last (empty ones included), per frame the ids and the similarity matrix — the IoU
    (``_calculate_box_ious``) with ``iou``, else the centre similarity (``_calculate_euclidean_similarity``,
    ``zero_distance = threshold``). Needs TrackEval."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # it warns about its optional dataset dependencies
        from trackeval.datasets._base_dataset import _BaseDataset
    gt, pred = gt.sorted(), pred.sorted()
    _, g = np.unique(gt.id, return_inverse=True)
    _, h = np.unique(pred.id, return_inverse=True)
    both = np.concatenate([gt.frame, pred.frame])
    frames = np.arange(both.min(), both.max() + 2) if both.size else np.arange(3)
    data = {"gt_ids": [], "tracker_ids": [], "similarity_scores": [], "num_timesteps": frames.size - 1,
            "num_gt_dets": gt.size, "num_tracker_dets": pred.size,
            "num_gt_ids": int(g.max(initial=-1)) + 1, "num_tracker_ids": int(h.max(initial=-1)) + 1}
    g_split, p_split = np.searchsorted(gt.frame, frames), np.searchsorted(pred.frame, frames)
    for t in range(frames.size - 1):
        a, b = slice(g_split[t], g_split[t + 1]), slice(p_split[t], p_split[t + 1])
        if iou is not None:
            s = _BaseDataset._calculate_box_ious(gt.boxes()[a], pred.boxes()[b], box_format="xywh")
        else:
            s = _BaseDataset._calculate_euclidean_similarity(gt.centers()[a], pred.centers()[b],
                                                             zero_distance=threshold)
        data["gt_ids"].append(g[a])
        data["tracker_ids"].append(h[b])
        data["similarity_scores"].append(s)
    return data


def trackeval_hota(data: dict) -> dict:
    """TrackEval's ``HOTA().eval_sequence`` on :func:`trackeval_data`'s dict."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from trackeval.metrics import HOTA

        return HOTA().eval_sequence(data)


def measure(gt: MOTData | None = None, pred: MOTData | None = None, frames: int = 512, objects: int = 85,
            repeats: int = 3, seed: int = 0) -> BenchResult:
    """Time :func:`~torchtrack.metrics.hota` (best of ``repeats``) and TrackEval's metric class, when installed,
    on ``gt``/``pred`` or, when they are None, on the synthetic workload; ``extra`` says whether the scores
    agree to 1e-9 (None: no reference)."""
    if gt is None or pred is None:
        gt, pred = workload(frames, objects, seed)
    n_frames = int(np.unique(gt.frame).size)
    ours = best_time(lambda: hota(gt, pred, threshold=10.0), repeats=repeats)
    scores = hota(gt, pred, threshold=10.0)
    extra = {"seconds": ours, "truth_points": gt.size, "predictions": pred.size, "HOTA": scores["HOTA"]}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import trackeval  # noqa: F401  (test-only dependency, optional here)
    except ImportError:
        return BenchResult(_name(n_frames, gt, pred), n_frames / ours, "TrackEval (not installed)", 0.0,
                           "frames", {**extra, "scores_agree": None})
    t0 = time.perf_counter()
    data = trackeval_data(gt, pred, threshold=10.0)
    prepare = time.perf_counter() - t0
    ref_time = best_time(lambda: trackeval_hota(data), repeats=repeats)
    ref = trackeval_hota(data)
    agree = all(abs(scores[key] - float(np.mean(ref[key]))) <= 1e-9 for key in KEYS)
    return BenchResult(_name(n_frames, gt, pred), n_frames / ours, "TrackEval 1.3 HOTA metric class",
                       n_frames / ref_time, "frames",
                       {**extra, "reference_seconds": ref_time, "reference_prepare_seconds": prepare,
                        "ratio_with_preparation": (ref_time + prepare) / ours, "scores_agree": agree})


def _name(n_frames: int, gt: MOTData, pred: MOTData) -> str:
    return f"HOTA (centre similarity, D = 10 px), {n_frames} frames, {gt.size} truth points, {pred.size} predictions"
