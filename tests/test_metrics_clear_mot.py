"""CLEAR-MOT / MT-PT-ML / FRAG / IDF1 against py-motmetrics (test-only reference) and hand-worked cases."""

import importlib
import warnings
from pathlib import Path

import numpy as np
import pytest

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points, read_mot
from torchtrack.metrics import clear_mot

clear_mot_module = importlib.import_module("torchtrack.metrics.clear_mot")

mm = pytest.importorskip("motmetrics")
MM_DATA = Path(mm.__file__).parent / "data"

COUNTS = {"FP": "num_false_positives", "FN": "num_misses", "IDS": "num_switches", "FRAG": "num_fragmentations",
          "MT": "mostly_tracked", "PT": "partially_tracked", "ML": "mostly_lost", "TP": "num_detections",
          "GT": "num_unique_objects", "GT_objects": "num_objects", "predictions": "num_predictions"}
RATIOS = {"MOTA": "mota", "MOTP": "motp", "IDF1": "idf1", "IDP": "idp", "IDR": "idr",
          "precision": "precision", "recall": "recall"}


def motmetrics_reference(gt, pred, threshold=10.0, iou=None) -> dict:
    """motmetrics' accumulator fed frame by frame (objects in id order) with its own distance functions."""
    acc = mm.MOTAccumulator()
    gt, pred = gt.sorted(), pred.sorted()
    for f in np.union1d(gt.frame, pred.frame):
        a, b = gt.frame == f, pred.frame == f
        if iou is not None:
            # mm.distances.iou_matrix calls np.asfarray (gone in numpy 2); same formula via its boxiou
            o, h = gt.boxes()[a], pred.boxes()[b]
            d = 1 - mm.distances.boxiou(o[:, None], h[None, :]) if a.any() and b.any() else np.empty((0, 0))
            d = np.where(d > 1 - iou, np.nan, d)
        else:
            # squared distances gated at threshold**2; MOTP in pixels needs the square root
            d = np.sqrt(mm.distances.norm2squared_matrix(gt.centers()[a], pred.centers()[b],
                                                         max_d2=threshold**2))
        acc.update(gt.id[a], pred.id[b], d, frameid=int(f))
    names = sorted(set(COUNTS.values()) | set(RATIOS.values()) | {"num_frames"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mm.metrics.create().compute(acc, metrics=names, return_dataframe=False)


def assert_same(ours: dict, ref: dict) -> None:
    for k, r in COUNTS.items():
        assert ours[k] == int(ref[r]), (k, ours[k], ref[r])
    for k, r in RATIOS.items():
        assert ours[k] == pytest.approx(float(ref[r]), abs=1e-6, nan_ok=True), k
    assert ours["frames"] == int(ref["num_frames"])


@pytest.mark.parametrize("name", ["TUD-Campus", "TUD-Stadtmitte"])
@pytest.mark.parametrize("iou", [0.5, 0.3])
def test_shipped_motchallenge_files_iou_mode(name, iou):
    gt, pred = read_mot(MM_DATA / name / "gt.txt"), read_mot(MM_DATA / name / "test.txt")
    assert_same(clear_mot(gt, pred, iou=iou), motmetrics_reference(gt, pred, iou=iou))


def crowded(seed: int, frames=40, objects=25, noise=4.0):
    """Random walks in a small area (many pairs within the gate), misses, false tracks, id confusion."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 80, (objects, 2))
    vel = rng.normal(0, 2, (objects, 2))
    alive = rng.random(objects) < 0.7
    fr, ids, xy = [], [], []
    for t in range(1, frames + 1):
        if t % 7 == 0:  # a run of empty frames with nobody present
            continue
        pos = pos + vel + rng.normal(0, 1, pos.shape)
        alive ^= rng.random(objects) < 0.05
        idx = np.flatnonzero(alive)
        fr += [t] * idx.size
        ids += list(idx)
        xy.append(pos[idx])
    fr, ids, xy = np.array(fr), np.array(ids), np.concatenate(xy)
    gt = from_points(fr, ids, xy[:, 0], xy[:, 1])
    keep = rng.random(fr.size) < 0.85
    pid = np.where(rng.random(fr.size) < 0.15, ids + 100, ids)  # identity switches
    noisy = xy + rng.normal(0, noise, xy.shape)
    n_false = 60
    pred = from_points(np.concatenate([fr[keep], rng.integers(1, frames + 3, n_false)]),
                       np.concatenate([pid[keep], 1000 + np.arange(n_false)]),
                       np.concatenate([noisy[keep, 0], rng.uniform(0, 80, n_false)]),
                       np.concatenate([noisy[keep, 1], rng.uniform(0, 80, n_false)]))
    return gt, pred


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("threshold", [5.0, 10.0])
def test_random_points_centre_mode(seed, threshold):
    gt, pred = crowded(seed)
    ref = motmetrics_reference(gt, pred, threshold=threshold)
    assert int(ref["num_switches"]) > 0 and int(ref["num_fragmentations"]) > 0  # the case is not trivial
    assert_same(clear_mot(gt, pred, threshold=threshold), ref)


@pytest.mark.parametrize("seed", range(3))
def test_sparse_path_gives_the_same_scores(seed, monkeypatch):
    gt, pred = crowded(seed)
    dense = clear_mot(gt, pred, threshold=8.0)
    monkeypatch.setattr(clear_mot_module, "DENSE_LIMIT", 0)
    sparse = clear_mot(gt, pred, threshold=8.0)
    assert sparse == pytest.approx(dense, abs=1e-9)
    gt_b, pred_b = read_mot(MM_DATA / "TUD-Campus" / "gt.txt"), read_mot(MM_DATA / "TUD-Campus" / "test.txt")
    assert_same(clear_mot(gt_b, pred_b, iou=0.5), motmetrics_reference(gt_b, pred_b, iou=0.5))


def test_hand_worked_swap():
    # two objects on parallel lines 20 px apart; the tracker swaps their labels at frame 3, and loses
    # object 1 at frame 5 only
    frames = [1, 1, 2, 2, 3, 3, 4, 4, 5, 6, 6]
    gt = from_points([1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6], [1, 2] * 6, [0, 0] * 6, [0, 20] * 6)
    pred = from_points(frames, [7, 8, 7, 8, 8, 7, 8, 7, 7, 8, 7], [1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1],
                       [0, 20, 0, 20, 0, 20, 0, 20, 20, 0, 20])
    r = clear_mot(gt, pred, threshold=10.0)
    assert (r["TP"], r["FN"], r["FP"], r["IDS"], r["FRAG"]) == (11, 1, 0, 2, 1)
    assert r["MOTA"] == pytest.approx(1 - 3 / 12)
    assert r["MOTP"] == pytest.approx(1.0)
    assert (r["MT"], r["PT"], r["ML"], r["GT"]) == (2, 0, 0, 2)
    # within the gate: object 1 with 7 on frames 1-2 and with 8 on 3, 4, 6; object 2 with 8 on 1-2 and
    # with 7 on 3-6; the best global id matching is 1<->8, 2<->7: IDTP = 3 + 4
    assert r["IDF1"] == pytest.approx(2 * 7 / (12 + 11))


def test_empty_frames_and_empty_inputs():
    gt = from_points([1, 50, 100], [1, 1, 1], [5, 5, 5], [5, 5, 5])
    none = from_points([], [], [], [])
    r = clear_mot(gt, none)
    assert (r["FN"], r["TP"], r["FP"], r["frames"], r["ML"]) == (3, 0, 0, 3, 1)
    assert r["MOTA"] == 0.0 and np.isnan(r["MOTP"])
    r = clear_mot(none, gt)
    assert r["FP"] == 3 and np.isnan(r["MOTA"]) and r["GT"] == 0
    r = clear_mot(gt, gt)
    assert (r["MOTA"], r["MOTP"], r["IDF1"], r["FRAG"], r["MT"]) == (1.0, 0.0, 1.0, 0, 1)


def test_tens_of_thousands_in_one_frame():
    rng = np.random.default_rng(0)
    n = 30000  # a dense (n, n) matrix would need 7 GB
    xy = rng.uniform(0, 20000, (n, 2))
    gt = from_points(np.ones(n, int), np.arange(n), xy[:, 0], xy[:, 1])
    noisy = xy + rng.normal(0, 0.5, xy.shape)
    pred = from_points(np.ones(n, int), np.arange(n) + 5, noisy[:, 0], noisy[:, 1])
    r = clear_mot(gt, pred, threshold=10.0)
    assert r["TP"] + r["FN"] == n and r["TP"] > 0.99 * n
    assert r["MOTP"] == pytest.approx(0.5 * np.sqrt(np.pi / 2), rel=0.05)  # mean of a Rayleigh(0.5)


def test_bad_arguments():
    gt = from_points([1], [1], [0], [0])
    with pytest.raises(TorchtrackError, match="negative ids"):
        clear_mot(gt, from_points([1], [-1], [0], [0]))
    with pytest.raises(TorchtrackError, match="threshold"):
        clear_mot(gt, gt, threshold=0)
    with pytest.raises(TorchtrackError, match="iou"):
        clear_mot(gt, gt, iou=1.5)
