"""HOTA (Luiten et al., "HOTA: a higher order metric for evaluating multi-object tracking", IJCV 2021).

Computed as TrackEval's ``HOTA`` metric class does, so the numbers agree with it (tests compare them):

1. **Global alignment.** For every frame with similarities ``S`` (objects × hypotheses), each pair adds
   ``S_ij / (sum_k S_kj + sum_k S_ik - S_ij)`` (0 where that denominator is <= eps) to its id pair's
   co-occurrence ``P``; with ``n_o``, ``n_h`` the number of frames each id is present in, the alignment
   score is ``A = P / (n_o + n_h - P)``.
2. **Per-frame matching.** In every frame with both objects and hypotheses, one Hungarian assignment
   maximises ``A * S``; for each ``alpha`` in 0.05, 0.10, ..., 0.95 the assigned pairs with
   ``S >= alpha - eps`` are the true positives TP(alpha); the other objects are FN, the other hypotheses FP.
3. **Scores per alpha**: ``DetRe = TP / (TP + FN)``, ``DetPr = TP / (TP + FP)``,
   ``DetA = TP / (TP + FN + FP)``; with ``c`` the number of TPs of an id pair,
   ``AssA = sum_TP c / (n_o + n_h - c) / TP``, ``AssRe = sum_TP c / n_o / TP``,
   ``AssPr = sum_TP c / n_h / TP``; ``HOTA = sqrt(DetA * AssA)``; ``LocA`` = mean ``S`` over the TPs
   (1 when there are none). Denominators are clamped at 1 (at 1e-10 for LocA), as TrackEval does.

The reported scores are the means of these over the 19 alphas. Similarities: **centre mode** (default)
``S = max(0, 1 - d / threshold)`` with ``d`` the distance between box centres in pixels (TrackEval's
euclidean similarity with ``zero_distance = threshold``); **IoU mode** the IoU of the boxes (TrackEval's
``_calculate_box_ious``, boxes of zero area overlap nothing). A frame with more than :data:`DENSE_LIMIT`
(object, hypothesis) pairs is matched through a k-d tree search for the pairs with ``S > 0`` and one
assignment per connected component: the same optimum in bounded memory (ties may break differently).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from torchtrack.association.assignment import by_component, gated_pairs
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import MOTData
from torchtrack.metrics.clear_mot import DENSE_LIMIT, scored_sets

ALPHAS = np.arange(0.05, 0.99, 0.05)
"""The 19 localisation thresholds alpha = 0.05, 0.10, ..., 0.95 (TrackEval's ``array_labels``)."""

KEYS = ("HOTA", "DetA", "AssA", "LocA", "DetRe", "DetPr", "AssRe", "AssPr")

_EPS = np.finfo(float).eps


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of boxes ``a`` (..., 4) and ``b`` (..., 4) in ``x, y, w, h``, broadcast over the leading axes;
    0 where a box has zero area. Corners and areas are formed as TrackEval forms them (``x + w`` first)."""
    a_min, a_max = a[..., :2], a[..., :2] + a[..., 2:]
    b_min, b_max = b[..., :2], b[..., :2] + b[..., 2:]
    inter = np.prod(np.maximum(np.minimum(a_max, b_max) - np.maximum(a_min, b_min), 0), axis=-1)
    area_a, area_b = np.prod(a_max - a_min, axis=-1), np.prod(b_max - b_min, axis=-1)
    union = area_a + area_b - inter
    ok = (area_a > _EPS) & (area_b > _EPS) & (union > _EPS)
    return np.where(ok, inter / np.where(union > _EPS, union, 1.0), 0.0)


def centre_similarity(a: np.ndarray, b: np.ndarray, threshold: float) -> np.ndarray:
    """``max(0, 1 - d / threshold)`` of centres ``a`` (..., 2) and ``b`` (..., 2), ``d`` Euclidean, broadcast."""
    return np.maximum(0.0, 1.0 - np.linalg.norm(a - b, axis=-1) / threshold)


def _frame_pairs(a: np.ndarray, b: np.ndarray, threshold: float, iou: bool) -> tuple[np.ndarray, ...]:
    """``(i, j, S_ij)`` of the pairs of features ``a`` (n, k), ``b`` (m, k) with similarity S > 0, in row-major
    order; a frame with more than :data:`DENSE_LIMIT` pairs is searched with k-d trees on the centres."""
    n, m = a.shape[0], b.shape[0]
    if n * m <= DENSE_LIMIT:
        s = box_iou(a[:, None], b[None, :]) if iou else centre_similarity(a[:, None], b[None, :], threshold)
        i, j = np.nonzero(s > 0)
        return i, j, s[i, j]
    if iou:
        # overlapping boxes have centres closer than the sum of their half diagonals
        radius = 0.5 * (np.hypot(a[:, 2], a[:, 3]).max() + np.hypot(b[:, 2], b[:, 3]).max())
        i, j, _ = gated_pairs(a[:, :2] + 0.5 * a[:, 2:], b[:, :2] + 0.5 * b[:, 2:], radius * (1 + 1e-9) + 1e-9)
        sim = box_iou(a[i], b[j])
    else:
        i, j, _ = gated_pairs(a, b, threshold)
        sim = centre_similarity(a[i], b[j], threshold)
    order = np.argsort(i * m + j)
    i, j, sim = i[order], j[order], sim[order]
    keep = sim > 0
    return i[keep], j[keep], sim[keep]


def _max_score(score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The assignment maximising the total of a dense block (NaN: no pair, score 0), solved as TrackEval does."""
    return linear_sum_assignment(-np.nan_to_num(score, nan=0.0))


def _assign(n: int, m: int, i: np.ndarray, j: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns assigned by the Hungarian algorithm maximising the total ``score`` of the pairs
    ``(i, j)`` (all other pairs score 0); only assigned pairs among ``(i, j)`` are returned, as positions
    into them. Dense frames give TrackEval's exact assignment; larger ones are solved per connected
    component of the pairs (the same optimum; ties may break differently)."""
    if i.size == 0:
        return np.zeros(0, np.int64)
    if n * m <= DENSE_LIMIT:
        dense = np.zeros((n, m))
        dense[i, j] = score
        r, k = _max_score(dense)
    else:
        r, k, _ = by_component(n, m, i, j, score, _max_score)
    pos = np.minimum(np.searchsorted(i * m + j, r * m + k), i.size - 1)
    return pos[(i[pos] == r) & (j[pos] == k)]


def hota(gt: MOTData, pred: MOTData, threshold: float = 10.0, iou: float | None = None,
         ignore: np.ndarray | None = None, count_zero_conf: bool = False) -> dict:
    """HOTA and its parts of tracker output ``pred`` against ground truth ``gt``.

    Args:
        gt: ground truth (ids >= 0, one line per object and frame).
        pred: tracker output (ids >= 0).
        threshold: ``D`` of the centre similarity ``max(0, 1 - d / D)`` in pixels (used unless ``iou``).
        iou: use the IoU of the boxes as the similarity; ``iou`` is then the IoU gate with which
            predictions are assigned to don't-care objects (TrackEval uses 0.5).
        ignore: optional (K,) bool over ``gt``'s lines marking don't-care objects; they, and the
            predictions assigned to them, are removed first (:func:`~torchtrack.metrics.clear_mot.drop_ignored`,
            same gate as :func:`~torchtrack.metrics.clear_mot.clear_mot`: ``d <= threshold`` or ``IoU >= iou``).
        count_zero_conf: score ground-truth lines whose ``conf`` is 0 as objects (by default they are
            don't-care objects, handled like ``ignore``, as ``clear_mot`` does).

    Returns:
        dict with :data:`KEYS` (fractions, means over :data:`ALPHAS`), ``alpha`` (19,) and ``per_alpha``:
        a dict of the same keys plus ``TP, FN, FP`` as (19,) float64 arrays.
    """
    gt, pred = scored_sets(gt, pred, threshold, iou, ignore, count_zero_conf, "HOTA")
    _, g = np.unique(gt.id, return_inverse=True)
    hyp_ids, h = np.unique(pred.id, return_inverse=True)
    n_hyp = max(hyp_ids.size, 1)
    gf, pf = (gt.boxes(), pred.boxes()) if iou is not None else (gt.centers(), pred.centers())
    frames = np.intersect1d(gt.frame, pred.frame)
    g_lo, g_hi = np.searchsorted(gt.frame, frames, "left"), np.searchsorted(gt.frame, frames, "right")
    p_lo, p_hi = np.searchsorted(pred.frame, frames, "left"), np.searchsorted(pred.frame, frames, "right")

    # pass 1: similarity-weighted co-occurrence of id pairs (step 1), over the pairs with S > 0
    pairs, keys, soft = [], [], []
    for a, b, c, e in zip(g_lo, g_hi, p_lo, p_hi):
        i, j, sim = _frame_pairs(gf[a:b], pf[c:e], threshold, iou is not None)
        row_sum = np.bincount(i, weights=sim, minlength=b - a)
        col_sum = np.bincount(j, weights=sim, minlength=e - c)
        denom = col_sum[j] + row_sum[i] - sim
        pairs.append((i, j, sim))
        keys.append(g[a + i] * n_hyp + h[c + j])
        soft.append(sim / np.where(denom > _EPS, denom, np.inf))
    gt_count = np.bincount(g).astype(np.float64)
    hyp_count = np.bincount(h).astype(np.float64)
    pair_keys, pair_of = np.unique(np.concatenate(keys) if keys else np.zeros(0, np.int64), return_inverse=True)
    co = np.bincount(pair_of, weights=np.concatenate(soft) if soft else None, minlength=pair_keys.size)
    alignment = co / (gt_count[pair_keys // n_hyp] + hyp_count[pair_keys % n_hyp] - co)

    # pass 2: per-frame Hungarian on A * S (step 2); the TPs of every alpha at once
    offsets = np.cumsum([0] + [k.size for k in keys])
    match_keys, match_sims = [], []
    for t, (i, j, sim) in enumerate(pairs):
        won = _assign(g_hi[t] - g_lo[t], p_hi[t] - p_lo[t], i, j,
                      alignment[pair_of[offsets[t]:offsets[t + 1]]] * sim)
        match_sims.append(sim[won])
        match_keys.append(keys[t][won])
    m_sims = np.concatenate(match_sims) if match_sims else np.zeros(0)
    m_keys = np.concatenate(match_keys) if match_keys else np.zeros(0, np.int64)
    hit = m_sims[:, None] >= ALPHAS[None, :] - _EPS  # (matches, 19)
    tp = hit.sum(0).astype(np.float64)
    fn, fp = gt.size - tp, pred.size - tp
    loc = (m_sims[:, None] * hit).sum(0)

    # step 3: association per alpha from the TP count c of each id pair
    uniq, pair = np.unique(m_keys, return_inverse=True)
    c = np.zeros((uniq.size, ALPHAS.size))
    np.add.at(c, pair, hit)
    n_o, n_h = gt_count[uniq // n_hyp][:, None], hyp_count[uniq % n_hyp][:, None]
    per_tp = np.maximum(1.0, tp)
    ass_a = (c * c / np.maximum(1.0, n_o + n_h - c)).sum(0) / per_tp
    ass_re = (c * c / np.maximum(1.0, n_o)).sum(0) / per_tp
    ass_pr = (c * c / np.maximum(1.0, n_h)).sum(0) / per_tp
    return _scores(tp, fn, fp, ass_a, ass_re, ass_pr, np.maximum(1e-10, loc) / np.maximum(1e-10, tp))


def _scores(tp: np.ndarray, fn: np.ndarray, fp: np.ndarray, ass_a: np.ndarray, ass_re: np.ndarray,
            ass_pr: np.ndarray, loc_a: np.ndarray) -> dict:
    """The result of :func:`hota` from the per-alpha (19,) counts and association and localisation scores."""
    det_a = tp / np.maximum(1.0, tp + fn + fp)
    per_alpha = {
        "HOTA": np.sqrt(det_a * ass_a), "DetA": det_a, "AssA": ass_a, "LocA": loc_a,
        "DetRe": tp / np.maximum(1.0, tp + fn), "DetPr": tp / np.maximum(1.0, tp + fp),
        "AssRe": ass_re, "AssPr": ass_pr, "TP": tp, "FN": fn, "FP": fp,
    }
    return {**{key: float(per_alpha[key].mean()) for key in KEYS}, "alpha": ALPHAS.copy(), "per_alpha": per_alpha}


def combine(results: Sequence[dict]) -> dict:
    """HOTA of several sequences together (results of :func:`hota`), as TrackEval's ``combine_sequences``: TP,
    FN and FP summed per alpha; AssA, AssRe, AssPr and LocA the means weighted by each sequence's TP; the
    detection scores and HOTA recomputed from those."""
    if not results:
        raise TorchtrackError("HOTA: no sequences to combine")
    per = [r["per_alpha"] for r in results]
    tp, fn, fp = (sum(p[key] for p in per) for key in ("TP", "FN", "FP"))
    weighted = {key: sum(p[key] * p["TP"] for p in per) for key in ("AssA", "AssRe", "AssPr", "LocA")}
    ass_a, ass_re, ass_pr = (weighted[key] / np.maximum(1.0, tp) for key in ("AssA", "AssRe", "AssPr"))
    return _scores(tp, fn, fp, ass_a, ass_re, ass_pr, np.maximum(1e-10, weighted["LocA"]) / np.maximum(1e-10, tp))
