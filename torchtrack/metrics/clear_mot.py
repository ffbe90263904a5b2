"""CLEAR-MOT (Bernardin & Stiefelhagen 2008), MT/PT/ML, fragmentations and IDF1 (Ristani et al. 2016).

The per-frame matching is the one py-motmetrics' ``MOTAccumulator.update`` implements, so the counts agree
with it exactly (tests compare them). For every frame, in increasing frame order:

1. **Keep correspondences.** Each ground-truth object ``o`` (in increasing id order) that was last matched
   to hypothesis ``h`` — in any earlier frame — is matched to ``h`` again if ``h`` is present and still
   within the threshold (and not already taken in this step).
2. **Hungarian for the rest.** The remaining objects and hypotheses are assigned by a minimum-cost
   assignment (scipy's ``linear_sum_assignment``) over the pairs within the threshold; pairs beyond it get
   motmetrics' large finite cost (``2 r c + 1``), so the number of matches is maximised first and the
   total distance minimised second. A match of ``o`` to an ``h`` different from its last partner is an
   identity switch (IDS); its distance still counts in MOTP.
3. Unmatched objects are misses (FN), unmatched hypotheses false positives (FP).

Distances: **centre mode** (default) uses the Euclidean distance between box centres in pixels; a pair
matches when ``d <= threshold`` (the paper's 10 px) and the assignment cost is ``d`` (motmetrics'
``'euc'``, i.e. ``sqrt(norm2squared_matrix(max_d2=threshold**2))``). **IoU mode** (``iou=T``) uses
``1 - IoU`` and matches when ``1 - IoU <= 1 - T`` (motmetrics' ``iou_matrix(max_iou=1-T)``).

Scores, with ``GT_objects`` the number of ground-truth boxes summed over frames:

- ``MOTA = 1 - (FN + FP + IDS) / GT_objects``; ``MOTP`` = mean distance over matches (px in centre
  mode, mean ``1 - IoU`` in IoU mode); ``TP`` = matches (IDS included);
  ``precision = TP / (TP + FP)``, ``recall = TP / GT_objects``.
- ``MT``/``PT``/``ML``: ground-truth trajectories matched in at least 80 % / 20–80 % / under 20 % of the
  frames they are present in (motmetrics' thresholds: ``ML`` is ``ratio < 0.2``, ``PT`` is
  ``0.2 <= ratio < 0.8``). ``GT`` is the number of ground-truth trajectories.
- ``FRAG``: times a trajectory goes from matched to unmatched and is matched again later.
- ``IDF1 = 2 IDTP / (GT_objects + predictions)``, where ``IDTP`` is the number of (frame, object,
  hypothesis) co-occurrences within the threshold kept by the best one-to-one global matching of
  trajectory ids to hypothesis ids (Ristani et al. 2016); ``IDP`` and ``IDR`` likewise.

Ratios with a zero denominator are NaN. Frames are the union of the frames present in either file.
A frame with both many objects and many hypotheses (more than :data:`DENSE_LIMIT` pairs) is matched
through a sparse neighbour search and per-connected-component assignments, so memory stays bounded; the
result is the same optimum (ties may break differently from motmetrics).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from torchtrack.association.pairs import by_component
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import MOTData

DENSE_LIMIT = 1 << 22
"""Largest number of (object, hypothesis) pairs of one frame matched with a dense distance matrix."""

KEYS = ("MOTA", "MOTP", "IDF1", "MT", "PT", "ML", "FP", "FN", "IDS", "FRAG", "TP", "GT",
        "precision", "recall", "frames")


def _div(a: float, b: float) -> float:
    return float(a) / float(b) if b != 0 else float("nan")


def _iou_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``1 - IoU`` of boxes ``a`` (..., 4) and ``b`` (..., 4) in ``x, y, w, h`` (motmetrics' boxiou)."""
    a_min, a_max = a[..., :2], a[..., :2] + a[..., 2:]
    b_min, b_max = b[..., :2], b[..., :2] + b[..., 2:]
    i_vol = np.prod(np.maximum(np.minimum(a_max, b_max) - np.maximum(a_min, b_min), 0), axis=-1)
    u_vol = np.prod(np.maximum(a_max - a_min, 0), axis=-1) + np.prod(np.maximum(b_max - b_min, 0), axis=-1)
    u_vol = u_vol - i_vol
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = np.where(i_vol == 0, 0.0, i_vol / np.where(u_vol == 0, 1.0, u_vol))
    return 1.0 - iou


class _Distance:
    """Pair distances and the matching gate for one evaluation mode."""

    def __init__(self, threshold: float, iou: float | None):
        self.iou = iou
        self.threshold = threshold

    def features(self, data: MOTData) -> np.ndarray:
        return data.boxes() if self.iou is not None else data.centers()

    def dense(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(n, m) distances, NaN where the pair may not match."""
        if self.iou is not None:
            d = _iou_distance(a[:, None], b[None, :])
            return np.where(d > 1.0 - self.iou, np.nan, d)
        dx, dy = a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1]
        d2 = dx * dx + dy * dy
        d2[d2 > self.threshold**2] = np.nan
        return np.sqrt(d2)

    def pairs(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sparse (i, j, distance) of the pairs that may match, found with a k-d tree on the centres."""
        if self.iou is not None:
            ca, cb = a[:, :2] + 0.5 * a[:, 2:], b[:, :2] + 0.5 * b[:, 2:]
            # overlapping boxes have centres closer than the sum of their half diagonals
            radius = 0.5 * (np.hypot(a[:, 2], a[:, 3]).max() + np.hypot(b[:, 2], b[:, 3]).max())
        else:
            ca, cb, radius = a, b, self.threshold
        sdm = cKDTree(ca).sparse_distance_matrix(cKDTree(cb), radius * (1 + 1e-9) + 1e-9, output_type="ndarray")
        i, j = sdm["i"].astype(np.int64), sdm["j"].astype(np.int64)
        if self.iou is not None:
            d = _iou_distance(a[i], b[j])
            keep = ~(d > 1.0 - self.iou)
        else:
            d2 = np.sum((a[i] - b[j]) ** 2, axis=-1)
            keep = ~(d2 > self.threshold**2)
            d = np.sqrt(d2)
        return i[keep], j[keep], d[keep]


def _lsa_with_gaps(costs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-cost assignment where NaN marks forbidden pairs (motmetrics' ``lsa_solve_scipy``)."""
    valid = np.isfinite(costs)
    if not valid.any():
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    c = np.abs(costs[valid]).max() + 1
    finite = np.where(valid, costs, 2 * min(costs.shape) * c + 1) if not valid.all() else costs
    r, k = linear_sum_assignment(finite)
    ok = valid[r, k]
    return r[ok], k[ok]


def _match_dense(dist: np.ndarray, masked_rows: np.ndarray, masked_cols: np.ndarray):
    costs = dist.copy()
    costs[masked_rows, :] = np.nan
    costs[:, masked_cols] = np.nan
    r, k = _lsa_with_gaps(costs)
    return r, k, dist[r, k]


def _match_sparse(n: int, m: int, i: np.ndarray, j: np.ndarray, d: np.ndarray,
                  masked_rows: np.ndarray, masked_cols: np.ndarray):
    keep = ~masked_rows[i] & ~masked_cols[j]
    return by_component(n, m, i[keep], j[keep], d[keep], _lsa_with_gaps)


def _max_weight(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maximum-weight matching of a dense block (NaN = no pair = weight 0)."""
    return linear_sum_assignment(np.nan_to_num(weights, nan=0.0), maximize=True)


def _idtp(keys: np.ndarray, n_hyp: int) -> int:
    """IDTP: the largest number of co-occurrences kept by a one-to-one map of object ids to hypothesis ids."""
    if keys.size == 0:
        return 0
    keys, counts = np.unique(keys, return_counts=True)
    uo, ro = np.unique(keys // n_hyp, return_inverse=True)
    uh, rh = np.unique(keys % n_hyp, return_inverse=True)
    if uo.size * uh.size <= DENSE_LIMIT:
        weights = np.zeros((uo.size, uh.size))
        weights[ro, rh] = counts
        r, k = linear_sum_assignment(weights, maximize=True)
        return int(weights[r, k].sum())
    _, _, w = by_component(uo.size, uh.size, ro, rh, counts.astype(np.float64), _max_weight)
    return int(np.nansum(w))


def scored_sets(gt: MOTData, pred: MOTData, threshold: float, iou: float | None, ignore: np.ndarray | None,
                count_zero_conf: bool, metric: str) -> tuple[MOTData, MOTData]:
    """The arguments of a tracking metric (``metric``: its name, for the errors) checked, and the ``(gt, pred)``
    it scores: the don't-care objects (``ignore``, and gt lines with ``conf`` 0 unless ``count_zero_conf``)
    removed with the predictions matched to them (:func:`drop_ignored`), both sorted by frame and id."""
    if iou is None and not threshold > 0:
        raise TorchtrackError(f"threshold must be positive, got {threshold}")
    if iou is not None and not 0 < iou <= 1:
        raise TorchtrackError(f"iou must be in (0, 1], got {iou}")
    for data, what in ((gt, "ground truth"), (pred, "prediction")):
        if data.size and data.id.min() < 0:
            raise TorchtrackError(f"{what} has negative ids (unlabelled detections?); {metric} needs track ids")
    if not count_zero_conf and np.any(gt.conf == 0):
        ignore = (gt.conf == 0) | (False if ignore is None else np.asarray(ignore, dtype=bool))
    if ignore is not None:
        gt, pred = drop_ignored(gt, pred, ignore, threshold, iou)
    return gt.sorted(), pred.sorted()


def drop_ignored(gt: MOTData, pred: MOTData, ignore: np.ndarray, threshold: float = 10.0,
                 iou: float | None = None) -> tuple[MOTData, MOTData]:
    """Remove don't-care objects the MOTChallenge way: per frame, the predictions assigned (Hungarian within
    the gate, over all objects of the frame) to an ignored object are removed, then the ignored objects.

    ``ignore`` is a (K,) bool over ``gt``'s lines; returns the kept ``(gt, pred)``, sorted by frame and id.
    """
    metric = _Distance(float(threshold), iou)
    ignore = np.asarray(ignore, dtype=bool)
    if ignore.shape != (gt.size,):
        raise TorchtrackError(f"ignore must have one entry per ground-truth line ({gt.size}), got {ignore.shape}")
    order = np.lexsort((gt.id, gt.frame))
    gt, ignore = gt.select(order), ignore[order]
    pred = pred.sorted()
    keep = np.ones(pred.size, dtype=bool)
    gf, pf = metric.features(gt), metric.features(pred)
    for f in np.unique(gt.frame[ignore]):
        a, b = np.searchsorted(gt.frame, f, "left"), np.searchsorted(gt.frame, f, "right")
        c, e = np.searchsorted(pred.frame, f, "left"), np.searchsorted(pred.frame, f, "right")
        if e == c:
            continue
        n, m = b - a, e - c
        if n * m <= DENSE_LIMIT:
            r, k = _lsa_with_gaps(metric.dense(gf[a:b], pf[c:e]))
        else:
            pi, pj, pd = metric.pairs(gf[a:b], pf[c:e])
            r, k, _ = by_component(n, m, pi, pj, pd, _lsa_with_gaps)
        keep[c + k[ignore[a + r]]] = False
    return gt.select(~ignore), pred.select(keep)


def clear_mot(gt: MOTData, pred: MOTData, threshold: float = 10.0, iou: float | None = None,
              ignore: np.ndarray | None = None, count_zero_conf: bool = False) -> dict:
    """CLEAR-MOT, MT/PT/ML, FRAG and IDF1 of tracker output ``pred`` against ground truth ``gt``.

    Args:
        gt: ground truth (ids >= 0, one line per object and frame).
        pred: tracker output (ids >= 0).
        threshold: centre-distance gate in pixels (used unless ``iou`` is given).
        iou: IoU gate ``T`` in (0, 1]; a pair matches when ``IoU >= T``.
        ignore: optional (K,) bool over ``gt``'s lines marking don't-care objects (e.g. the vehicles that
            are not moving, :func:`torchtrack.io.moving.moving_mask`): in each frame, predictions assigned
            to them (Hungarian, same gate) are dropped, and so are they, before scoring.
        count_zero_conf: score ground-truth lines whose ``conf`` is 0 as real objects. By default they are
            don't-care objects, as in MOTChallenge ground truth (``conf`` 0: ignore) and TrackEval: handled
            like ``ignore``, so a prediction on one is neither a hit nor a false positive.

    Returns:
        dict with :data:`KEYS` (``MOTA, MOTP, IDF1, MT, PT, ML, FP, FN, IDS, FRAG, TP, GT, precision,
        recall, frames``) plus ``IDP, IDR, GT_objects, predictions, IDTP``. Fractions are in [0, 1] (MOTA may
        be negative), counts are ints. The matching rule and definitions are in the module docstring.
    """
    gt, pred = scored_sets(gt, pred, threshold, iou, ignore, count_zero_conf, "CLEAR-MOT")
    metric = _Distance(float(threshold), iou)
    gt_ids, g = np.unique(gt.id, return_inverse=True)
    hyp_ids, h = np.unique(pred.id, return_inverse=True)
    n_obj, n_hyp = gt_ids.size, hyp_ids.size
    gf, pf = metric.features(gt), metric.features(pred)
    frames = np.union1d(gt.frame, pred.frame)
    g_lo, g_hi = np.searchsorted(gt.frame, frames, "left"), np.searchsorted(gt.frame, frames, "right")
    p_lo, p_hi = np.searchsorted(pred.frame, frames, "left"), np.searchsorted(pred.frame, frames, "right")

    last_partner = np.full(n_obj, -1, dtype=np.int64)  # motmetrics' ``m``: object -> last hypothesis
    slot = np.full(n_hyp, -1, dtype=np.int64)  # hypothesis -> its column in the current frame
    match_h = np.full(gt.size, -1, dtype=np.int64)  # per ground-truth line
    match_d = np.zeros(gt.size)
    switch = np.zeros(gt.size, dtype=bool)
    pair_keys = []  # (object, hypothesis) co-occurrences within the gate, for IDF1
    for a, b, c, e in zip(g_lo, g_hi, p_lo, p_hi):
        n, m = b - a, e - c
        if n == 0 or m == 0:
            continue
        oi, hj = g[a:b], h[c:e]
        dense = n * m <= DENSE_LIMIT
        if dense:
            dist = metric.dense(gf[a:b], pf[c:e])
            pi, pj = np.nonzero(np.isfinite(dist))
        else:
            pi, pj, pd = metric.pairs(gf[a:b], pf[c:e])
            pair_order = np.argsort(pi * m + pj)
            pi, pj, pd = pi[pair_order], pj[pair_order], pd[pair_order]
        pair_keys.append(oi[pi] * n_hyp + hj[pj])

        # 1. keep last correspondences still within the gate (first object in id order wins a column)
        slot[hj] = np.arange(m)
        prev = last_partner[oi]
        col = np.where(prev >= 0, slot[np.maximum(prev, 0)], -1)
        rows = np.flatnonzero(col >= 0)
        if dense:
            d_keep = dist[rows, col[rows]]
        elif pi.size:
            pos = np.minimum(np.searchsorted(pi * m + pj, rows * m + col[rows]), pi.size - 1)
            d_keep = np.where((pi[pos] == rows) & (pj[pos] == col[rows]), pd[pos], np.nan)
        else:
            d_keep = np.full(rows.size, np.nan)
        ok = np.isfinite(d_keep)
        rows, kcols, d_keep = rows[ok], col[rows][ok], d_keep[ok]
        _, first = np.unique(kcols, return_index=True)
        rows, kcols, d_keep = rows[first], kcols[first], d_keep[first]
        slot[hj] = -1
        masked_rows = np.zeros(n, dtype=bool)
        masked_cols = np.zeros(m, dtype=bool)
        masked_rows[rows] = True
        masked_cols[kcols] = True

        # 2. Hungarian for the rest
        if dense:
            r2, k2, d2 = _match_dense(dist, masked_rows, masked_cols)
        else:
            r2, k2, d2 = _match_sparse(n, m, pi, pj, pd, masked_rows, masked_cols)
        prev2 = last_partner[oi[r2]]
        switch[a + r2] = (prev2 >= 0) & (prev2 != hj[k2])

        rows, cols, d = np.concatenate([rows, r2]), np.concatenate([kcols, k2]), np.concatenate([d_keep, d2])
        match_h[a + rows] = hj[cols]
        match_d[a + rows] = d
        last_partner[oi[rows]] = hj[cols]

    tracked = match_h >= 0
    tp = int(tracked.sum())
    ids = int(switch.sum())
    n_gt_boxes, n_pred_boxes = gt.size, pred.size
    fn, fp = n_gt_boxes - tp, n_pred_boxes - tp

    # MT / PT / ML from the fraction of each trajectory's frames it is matched in
    life = np.bincount(g, minlength=n_obj)
    ratio = np.bincount(g, weights=tracked, minlength=n_obj) / np.maximum(life, 1)
    mt, ml = int((ratio >= 0.8).sum()), int((ratio < 0.2).sum())

    # fragmentations: matched -> unmatched transitions followed by a later match of the same trajectory
    order = np.lexsort((gt.frame, g))
    obj, f = g[order], tracked[order]
    last_tracked = np.full(n_obj, -1, dtype=np.int64)
    np.maximum.at(last_tracked, obj[f], np.flatnonzero(f))
    starts = np.flatnonzero((obj[1:] == obj[:-1]) & f[:-1] & ~f[1:]) + 1
    frag = int((starts < last_tracked[obj[starts]]).sum())

    # IDF1: best global one-to-one matching of trajectory ids to hypothesis ids
    idtp = _idtp(np.concatenate(pair_keys) if pair_keys else np.zeros(0, np.int64), n_hyp)

    counts = {"MT": mt, "PT": int(n_obj - mt - ml), "ML": ml, "FP": int(fp), "FN": int(fn), "IDS": ids,
              "FRAG": frag, "TP": tp, "GT": int(n_obj), "frames": int(frames.size), "GT_objects": int(n_gt_boxes),
              "predictions": int(n_pred_boxes), "IDTP": int(idtp)}
    return _with_ratios(counts, float(match_d[tracked].sum()))


COUNTS = ("MT", "PT", "ML", "FP", "FN", "IDS", "FRAG", "TP", "GT", "frames", "GT_objects", "predictions", "IDTP")
"""The integer counts of :func:`clear_mot`; every other score is a ratio of them (and the distance sum)."""


def _with_ratios(counts: dict, distance_sum: float) -> dict:
    """``counts`` (:data:`COUNTS`) with the scores that are ratios of them; ``distance_sum`` over the matches."""
    tp, n_gt, n_pred, idtp = counts["TP"], counts["GT_objects"], counts["predictions"], counts["IDTP"]
    return {"MOTA": 1.0 - _div(counts["FN"] + counts["FP"] + counts["IDS"], n_gt), "MOTP": _div(distance_sum, tp),
            "IDF1": _div(2 * idtp, n_gt + n_pred), **counts, "precision": _div(tp, tp + counts["FP"]),
            "recall": _div(tp, n_gt), "IDP": _div(idtp, n_pred), "IDR": _div(idtp, n_gt)}


def combine(results: Sequence[dict]) -> dict:
    """The scores of several sequences together, as TrackEval combines them: the :data:`COUNTS` summed (ids of
    different sequences are different trajectories), the ratios recomputed from the sums, MOTP the mean over
    all matches (each sequence's MOTP weighted by its TP)."""
    if not results:
        raise TorchtrackError("CLEAR-MOT: no sequences to combine")
    counts = {key: sum(int(r[key]) for r in results) for key in COUNTS}
    return _with_ratios(counts, sum(r["MOTP"] * r["TP"] for r in results if r["TP"] > 0))
