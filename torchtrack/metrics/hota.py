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
``_calculate_box_ious``, boxes of zero area overlap nothing).

No frame is a dense matrix and no step loops over frames: the frames go in blocks of about ``BLOCK_ROWS`` lines
(memory follows the block, not the sequence); in each, one search finds the pairs with ``S > 0`` of all its
frames (a sweep along ``x``, or a k-d tree where points line up), step 1 is sums over them (a first pass over
the blocks), and step 2 (a second pass, with the alignment of the whole sequence) solves
each connected component of the pairs (:func:`torchtrack.association.pairs.max_total_assignment`, small ones
all at once by enumeration): the optimum TrackEval's dense solve finds, in memory proportional to the pairs
(ties may break differently). :func:`combine` scores several sequences together as TrackEval does.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from torchtrack.association.pairs import max_total_assignment
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import MOTData
from torchtrack.metrics.clear_mot import scored_sets

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


_SWEEP_CANDIDATES = 32
"""The sweep of :func:`_pairs` is used while it tests at most this many candidates per point (plus 2**20)."""


def _candidates(frame_a: np.ndarray, xy_a: np.ndarray, frame_b: np.ndarray, xy_b: np.ndarray,
                radius: float) -> tuple[np.ndarray, np.ndarray] | None:
    """``(i, j)``: every point pair of the same frame with ``|x_i - x_j| <= radius`` (a sweep along ``x``: one
    sort and two binary searches); None when there would be more than :data:`_SWEEP_CANDIDATES` per point
    (points lined up along ``y``), where a k-d tree does better."""
    span = 2 * (np.abs(xy_a[:, 0]).max(initial=0) + np.abs(xy_b[:, 0]).max(initial=0) + radius) + 1
    key_a, key_b = frame_a * span + xy_a[:, 0], frame_b * span + xy_b[:, 0]  # frames far apart along x
    order = np.argsort(key_b, kind="stable")
    sorted_b = key_b[order]
    lo = np.searchsorted(sorted_b, key_a - radius, "left")
    count = np.searchsorted(sorted_b, key_a + radius, "right") - lo
    if count.sum() > _SWEEP_CANDIDATES * (key_a.size + key_b.size) + (1 << 20):
        return None
    first = np.repeat(lo - np.cumsum(count) + count, count)
    return np.repeat(np.arange(key_a.size), count), order[first + np.arange(count.sum())]


def _pairs(gt: MOTData, pred: MOTData, threshold: float, iou: bool) -> tuple[np.ndarray, ...]:
    """``(i, j, S)``: every line ``i`` of ``gt`` and ``j`` of ``pred`` of the same frame with similarity
    ``S > 0``, among the candidates of a sweep along ``x`` (:func:`_candidates`) or, where that would test
    too many, of one k-d tree search over all frames (the frame number a third coordinate, scaled so that
    points of different frames are farther apart than any pair that can score)."""
    ca, cb = gt.centers(), pred.centers()
    if iou:  # overlapping boxes have centres closer than the sum of their half diagonals
        radius = 0.5 * (np.hypot(gt.w, gt.h).max(initial=0) + np.hypot(pred.w, pred.h).max(initial=0))
    else:
        radius = threshold
    radius = radius * (1 + 1e-9) + 1e-9
    found = _candidates(gt.frame, ca, pred.frame, cb, radius)
    if found is None:
        span = 2 * radius + 1.0
        tree_a = cKDTree(np.column_stack([ca, gt.frame * span]), balanced_tree=False)
        tree_b = cKDTree(np.column_stack([cb, pred.frame * span]), balanced_tree=False)
        found = tree_a.sparse_distance_matrix(tree_b, radius, output_type="ndarray")
        found = found["i"].astype(np.int64), found["j"].astype(np.int64)
    i, j = found
    sim = box_iou(gt.boxes()[i], pred.boxes()[j]) if iou else centre_similarity(ca[i], cb[j], threshold)
    keep = sim > 0
    return i[keep], j[keep], sim[keep]


BLOCK_ROWS = 1 << 17
"""Ground-truth plus predicted lines per block of whole frames that :func:`hota` holds pairs for at once."""


def _blocks(gt: MOTData, pred: MOTData, block_rows: int) -> list[tuple[slice, slice]]:
    """Slices of ``gt`` and ``pred`` (both sorted by frame) over consecutive whole frames, each block about
    ``block_rows`` lines of both together (one frame at least)."""
    frames = np.union1d(np.unique(gt.frame), np.unique(pred.frame))
    g_end = np.searchsorted(gt.frame, frames, "right")
    p_end = np.searchsorted(pred.frame, frames, "right")
    ends = np.searchsorted(g_end + p_end, np.arange(block_rows, gt.size + pred.size, block_rows), "left")
    cuts = np.unique(np.concatenate([ends, [frames.size - 1]])) if frames.size else np.zeros(0, np.int64)
    out, g0, p0 = [], 0, 0
    for c in cuts:
        out.append((slice(g0, int(g_end[c])), slice(p0, int(p_end[c]))))
        g0, p0 = int(g_end[c]), int(p_end[c])
    return out


def hota(gt: MOTData, pred: MOTData, threshold: float = 10.0, iou: float | None = None,
         ignore: np.ndarray | None = None, count_zero_conf: bool = False, block_rows: int = BLOCK_ROWS) -> dict:
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
        block_rows: lines of both inputs per block of whole frames: steps 1 and 2 run block by block (two
            passes, step 2 with the alignment of all frames), so memory follows the block, not the sequence.

    Returns:
        dict with :data:`KEYS` (fractions, means over :data:`ALPHAS`), ``alpha`` (19,) and ``per_alpha``:
        a dict of the same keys plus ``TP, FN, FP`` as (19,) float64 arrays.
    """
    gt, pred = scored_sets(gt, pred, threshold, iou, ignore, count_zero_conf, "HOTA")
    _, g = np.unique(gt.id, return_inverse=True)
    hyp_ids, h = np.unique(pred.id, return_inverse=True)
    n_hyp = max(hyp_ids.size, 1)
    gt_count = np.bincount(g).astype(np.float64)
    hyp_count = np.bincount(h).astype(np.float64)
    blocks = _blocks(gt, pred, max(1, block_rows))

    def block_pairs(sg: slice, sp: slice) -> tuple[np.ndarray, ...]:
        i, j, sim = _pairs(gt.select(sg), pred.select(sp), threshold, iou is not None)
        return i, j, sim, g[sg][i] * n_hyp + h[sp][j]

    # step 1: similarity-weighted co-occurrence of id pairs, from the frames' row and column sums of S
    keys, sums = [np.zeros(0, np.int64)], [np.zeros(0)]
    for sg, sp in blocks:
        i, j, sim, key = block_pairs(sg, sp)
        row_sum = np.bincount(i, weights=sim, minlength=sg.stop - sg.start)
        col_sum = np.bincount(j, weights=sim, minlength=sp.stop - sp.start)
        denom = row_sum[i] + col_sum[j] - sim
        block_keys, of = np.unique(key, return_inverse=True)
        keys.append(block_keys)
        sums.append(np.bincount(of, weights=sim / np.where(denom > _EPS, denom, np.inf), minlength=block_keys.size))
    pair_keys, of = np.unique(np.concatenate(keys), return_inverse=True)
    co = np.bincount(of, weights=np.concatenate(sums), minlength=pair_keys.size)
    alignment = co / (gt_count[pair_keys // n_hyp] + hyp_count[pair_keys % n_hyp] - co)

    # step 2: the assignment maximising A * S in every frame (one per connected component of the pairs,
    # which never spans two frames); the TPs of every alpha at once, and the TP count c of each id pair
    tp, loc = np.zeros(ALPHAS.size), np.zeros(ALPHAS.size)
    c = np.zeros(pair_keys.size * ALPHAS.size)
    for sg, sp in blocks:
        i, j, sim, key = block_pairs(sg, sp)
        pair_of = np.searchsorted(pair_keys, key)
        won = max_total_assignment(sg.stop - sg.start, sp.stop - sp.start, i, j, alignment[pair_of] * sim)
        m_sims = sim[won]
        hit = m_sims[:, None] >= ALPHAS[None, :] - _EPS  # (matches, 19)
        tp += hit.sum(0)
        loc += (m_sims[:, None] * hit).sum(0)
        c += np.bincount((pair_of[won][:, None] * ALPHAS.size + np.arange(ALPHAS.size))[hit], minlength=c.size)
    fn, fp = gt.size - tp, pred.size - tp

    # step 3: association per alpha from the TP count c of each id pair
    c = c.reshape(pair_keys.size, ALPHAS.size)
    n_o, n_h = gt_count[pair_keys // n_hyp][:, None], hyp_count[pair_keys % n_hyp][:, None]
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
