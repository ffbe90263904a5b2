"""HOTA against TrackEval's HOTA metric class (test-only reference; skipped without it) and hand-worked cases."""

import importlib
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from torchtrack.bench.hota import trackeval_data, trackeval_hota
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import MOTData, concat_mot, empty_mot, from_points, read_mot
from torchtrack.metrics import drop_ignored
from torchtrack.metrics.hota import ALPHAS, KEYS, hota

hota_module = importlib.import_module("torchtrack.metrics.hota")


def trackeval_reference(gt: MOTData, pred: MOTData, threshold=10.0, iou=None) -> dict:
    """TrackEval's HOTA metric class on its per-sequence data built from the two tables (ids relabelled, every
    frame from the first to the last, empty ones included). Skips the test without TrackEval (test-only)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # it warns about its optional dataset dependencies
        pytest.importorskip("trackeval")
    return trackeval_hota(trackeval_data(gt, pred, threshold=threshold, iou=iou))


def assert_same(ours: dict, ref: dict) -> None:
    for key in KEYS:
        assert ours[key] == pytest.approx(float(np.mean(ref[key])), abs=1e-9, rel=0), key
        np.testing.assert_allclose(ours["per_alpha"][key], ref[key], rtol=0, atol=1e-9, err_msg=key)
    for key in ("TP", "FN", "FP"):
        np.testing.assert_array_equal(ours["per_alpha"][key], ref[f"HOTA_{key}"], err_msg=key)


def random_tracks(seed: int, frames=30, objects=12, noise=3.0, box=8.0):
    """Moving points with gaps (ids that disappear and reappear, empty frames), noisy predictions with
    identity swaps, missed objects and false alarms; box sizes vary so that IoU mode is not degenerate."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 60, (objects, 2))
    vel = rng.normal(0, 1.5, (objects, 2))
    alive = rng.random(objects) < 0.7
    fr, ids, xy = [], [], []
    for f in range(1, frames + 1):
        pos = pos + vel + rng.normal(0, 0.5, pos.shape)
        alive ^= rng.random(objects) < 0.1
        if f % 7 == 0:
            continue  # no ground truth at all in this frame
        fr.append(np.full(alive.sum(), f))
        ids.append(np.flatnonzero(alive))
        xy.append(pos[alive])
    fr, ids, xy = np.concatenate(fr), np.concatenate(ids), np.concatenate(xy)
    gt = from_points(fr, ids, xy[:, 0], xy[:, 1], box=box)
    gt = gt._replace(w=gt.w * rng.uniform(0.6, 1.6, gt.size), h=gt.h * rng.uniform(0.6, 1.6, gt.size))
    keep = (rng.random(fr.size) < 0.8) & (fr % 11 != 0)  # frames 11, 22: objects but no predictions
    pid = np.where(rng.random(fr.size) < 0.2, ids + 50, ids)
    n_false = frames // 2
    pf = np.concatenate([fr[keep], rng.integers(1, frames + 4, n_false)])
    pxy = np.concatenate([xy[keep] + rng.normal(0, noise, (keep.sum(), 2)), rng.uniform(0, 60, (n_false, 2))])
    pred = from_points(pf, np.concatenate([pid[keep], rng.integers(200, 205, n_false)]), pxy[:, 0], pxy[:, 1],
                       box=box)
    pred = pred._replace(w=pred.w * rng.uniform(0.6, 1.6, pred.size), h=pred.h * rng.uniform(0.6, 1.6, pred.size))
    # a prediction id seen twice in one frame is not a track: keep the first
    _, first = np.unique(pred.frame * 1000 + pred.id, return_index=True)
    return gt, pred.select(np.sort(first))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("threshold", [4.0, 10.0])
def test_random_sequences_centre_similarity(seed, threshold):
    gt, pred = random_tracks(seed)
    assert_same(hota(gt, pred, threshold=threshold), trackeval_reference(gt, pred, threshold=threshold))


@pytest.mark.parametrize("block_rows", [1, 7, 40])
@pytest.mark.parametrize("iou", [None, 0.5])
def test_frames_in_blocks_equal_the_whole_sequence(block_rows, iou):
    """Blocks of a frame (block_rows 1) up to several frames give TrackEval's scores, as one block does."""
    gt, pred = random_tracks(3, noise=1.5 if iou else 3.0)
    kw = {"iou": iou} if iou else {"threshold": 10.0}
    whole = hota(gt, pred, block_rows=gt.size + pred.size, **kw)
    blocks = hota(gt, pred, block_rows=block_rows, **kw)
    assert_same(blocks, trackeval_reference(gt, pred, **kw))
    for key in KEYS:
        np.testing.assert_allclose(blocks["per_alpha"][key], whole["per_alpha"][key], rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_random_sequences_iou_similarity(seed):
    gt, pred = random_tracks(seed, noise=1.5)
    assert_same(hota(gt, pred, iou=0.5), trackeval_reference(gt, pred, iou=0.5))


@pytest.mark.parametrize("name", ["TUD-Campus", "TUD-Stadtmitte"])
def test_shipped_motchallenge_files_iou(name):
    mm_data = Path(pytest.importorskip("motmetrics").__file__).parent / "data"
    gt, pred = read_mot(mm_data / name / "gt.txt"), read_mot(mm_data / name / "test.txt")
    assert not np.any(gt.conf == 0)
    ours = hota(gt, pred, iou=0.5)
    assert 0 < ours["HOTA"] < 1
    assert_same(ours, trackeval_reference(gt, pred, iou=0.5))


def test_tens_of_thousands_in_one_frame():
    n = 30000  # a dense (n, n) matrix would need 7 GB
    xy = 50.0 * np.stack(np.unravel_index(np.arange(n), (200, 150)), axis=1)  # a grid, 50 px apart
    gt = from_points(np.ones(n, int), np.arange(n), xy[:, 0], xy[:, 1])
    pred = from_points(np.ones(n, int), np.arange(n) + 5, xy[:, 0] + 1.3, xy[:, 1])  # 1.3 px off: S = 0.87
    r = hota(gt, pred, threshold=10.0)
    # isolated objects: every one matched with S = 0.87, a TP for alpha <= 0.85 (17 alphas)
    assert np.array_equal(r["per_alpha"]["TP"], np.where(np.arange(19) < 17, n, 0.0))
    assert r["DetA"] == pytest.approx(17 / 19) and r["AssA"] == pytest.approx(17 / 19)
    assert r["LocA"] == pytest.approx((17 * 0.87 + 2) / 19)


def test_empty_inputs():
    gt, pred = random_tracks(0)
    none = empty_mot()
    for a, b in ((gt, none), (none, pred), (none, none)):
        ours = hota(a, b)
        assert ours["HOTA"] == 0 and ours["DetA"] == 0 and ours["AssA"] == 0 and ours["LocA"] == 1
        assert np.all(ours["per_alpha"]["FN"] == a.size) and np.all(ours["per_alpha"]["FP"] == b.size)
    for a, b in ((gt, none), (none, pred), (none, none)):
        assert_same(hota(a, b), trackeval_reference(a, b))


def test_hand_worked_identity_switch():
    """One object over two frames, tracked by id 7 at its centre, then by id 8 at 3.8 px (S = 0.62).
    alpha <= 0.60 (12 alphas): TP 2, DetA 1; pairs (1, 7) and (1, 8) each have c = 1, n_o = 2, n_h = 1:
    AssA = (1 * 1/2 + 1 * 1/2) / 2 = 1/2, AssRe 1/2, AssPr 1, LocA (1 + 0.62) / 2.
    alpha >= 0.65 (7 alphas): TP 1, FN 1, FP 1: DetA 1/3, DetRe = DetPr = 1/2, AssA 1/2, AssRe 1/2, AssPr 1, LocA 1."""
    gt = from_points([1, 2], [1, 1], [20.0, 30.0], [20.0, 20.0])
    pred = from_points([1, 2], [7, 8], [20.0, 30.0], [20.0, 23.8])
    r = hota(gt, pred, threshold=10.0)
    assert np.array_equal(r["per_alpha"]["TP"], np.where(np.arange(19) < 12, 2.0, 1.0))
    assert r["DetA"] == pytest.approx((12 + 7 / 3) / 19, abs=1e-12)
    assert r["DetRe"] == pytest.approx((12 + 7 / 2) / 19, abs=1e-12)
    assert r["DetPr"] == pytest.approx((12 + 7 / 2) / 19, abs=1e-12)
    assert r["AssA"] == pytest.approx(0.5, abs=1e-12)
    assert r["AssRe"] == pytest.approx(0.5, abs=1e-12)
    assert r["AssPr"] == pytest.approx(1.0, abs=1e-12)
    assert r["LocA"] == pytest.approx((12 * 0.81 + 7) / 19, abs=1e-12)
    assert r["HOTA"] == pytest.approx((12 * math.sqrt(0.5) + 7 * math.sqrt(1 / 6)) / 19, abs=1e-12)
    assert r["alpha"] == pytest.approx(ALPHAS) and ALPHAS.size == 19


def test_alignment_prior_decides_the_match():
    """Frame 3 has two hypotheses equally close to the object: the Hungarian on A * S picks the one that
    followed it in frames 1-2 (higher alignment score A), so every TP belongs to one id pair and AssA is 1."""
    gt = from_points([1, 2, 3], [1, 1, 1], [10.0, 20.0, 30.0], [10.0, 10.0, 10.0])
    pred = from_points([1, 2, 3, 3], [5, 5, 5, 6], [10.0, 20.0, 30.0, 30.0], [10.0, 10.0, 12.0, 8.0])
    r = hota(gt, pred, threshold=10.0)
    assert r["per_alpha"]["AssA"][0] == pytest.approx(1.0)
    assert r["per_alpha"]["FP"][0] == 1


def test_zero_conf_ground_truth_is_dont_care():
    gt, pred = random_tracks(1)
    zero = gt.conf.copy()
    zero[::5] = 0
    marked = gt._replace(conf=zero)
    kept_gt, kept_pred = drop_ignored(gt, pred, zero == 0, threshold=10.0)
    assert_same(hota(marked, pred), trackeval_reference(kept_gt, kept_pred))
    assert hota(marked, pred, count_zero_conf=True)["DetA"] == pytest.approx(hota(gt, pred)["DetA"])


def test_bad_arguments():
    gt, pred = random_tracks(0)
    with pytest.raises(TorchtrackError, match="threshold"):
        hota(gt, pred, threshold=0.0)
    with pytest.raises(TorchtrackError, match="iou"):
        hota(gt, pred, iou=1.5)
    with pytest.raises(TorchtrackError, match="negative ids"):
        hota(concat_mot([gt, from_points([1], [-1], [0.0], [0.0])]), pred)


@pytest.mark.parametrize("iou", [False, True])
def test_sweep_and_kd_tree_find_the_same_pairs(iou, monkeypatch):
    gt, pred = random_tracks(3, frames=40, objects=30)
    sweep = hota_module._pairs(gt, pred, 10.0, iou)
    monkeypatch.setattr(hota_module, "_SWEEP_CANDIDATES", -(10**9))  # every search through the k-d tree
    tree = hota_module._pairs(gt, pred, 10.0, iou)
    assert sweep[0].size > 100
    order_a, order_b = np.lexsort(sweep[1::-1]), np.lexsort(tree[1::-1])
    for a, b in zip(sweep, tree):
        np.testing.assert_array_equal(a[order_a], b[order_b])
