"""The scoring call of every tracker command (``metrics.table.score``) and its Table 1: HOTA and IDF1 beside MOTA."""

import re

import numpy as np
import pytest

from torchtrack.io.mot import concat_mot, format_lines, from_points, read_mot
from torchtrack.metrics import clear_mot, hota
from torchtrack.metrics.hota import KEYS as HOTA_KEYS
from torchtrack.metrics.table import TABLE1_HEADER, format_table1, protocol, score, table1_row


def moving_tracks(seed: int, frames=25, objects=8):
    """Objects moving in [0, 100]², noisy predictions (σ 2 px) with missed objects, identity swaps and false alarms."""
    rng = np.random.default_rng(seed)
    start, vel = rng.uniform(0, 100, (objects, 2)), rng.normal(0, 1.0, (objects, 2))
    f = np.repeat(np.arange(1, frames + 1), objects)
    ids = np.tile(np.arange(objects), frames)
    xy = start[ids] + vel[ids] * f[:, None]
    gt = from_points(f, ids, xy[:, 0], xy[:, 1])
    seen = rng.random(f.size) < 0.85
    pid = np.where((f > frames // 2) & (ids < 2), 1 - ids, ids) + 10   # objects 0 and 1 swap identities halfway
    pxy = xy[seen] + rng.normal(0, 2.0, (seen.sum(), 2))
    found = from_points(f[seen], pid[seen], pxy[:, 0], pxy[:, 1])
    clutter = from_points(np.arange(1, frames + 1), np.full(frames, 99), *rng.uniform(0, 100, (2, frames)))
    return gt, concat_mot([found, clutter])


def test_table1_row_carries_the_hota_and_idf1_of_the_metrics():
    gt, pred = moving_tracks(0)
    m = score(gt, pred, threshold=10.0)
    pred = pred.as_written()                                           # what score() scores
    ref_hota, ref_clear = hota(gt, pred, threshold=10.0), clear_mot(gt, pred, threshold=10.0)
    assert {k: m[k] for k in HOTA_KEYS} == pytest.approx({k: ref_hota[k] for k in HOTA_KEYS}, abs=1e-12)
    assert 0.3 < m["HOTA"] < 0.9 and 0.3 < m["IDF1"] < 0.95          # neither trivial score
    assert all(type(m[k]) is float for k in ("MOTA", "IDF1", *HOTA_KEYS))
    row = dict(zip(TABLE1_HEADER, table1_row("x", {**m, "FPS": 1.0})))
    assert row["HOTA (%)"] == pytest.approx(100 * ref_hota["HOTA"], abs=1e-10)
    assert row["IDF1 (%)"] == pytest.approx(100 * ref_clear["IDF1"], abs=1e-10)
    assert row["MOTA (%)"] == pytest.approx(100 * ref_clear["MOTA"], abs=1e-10)


def test_threshold_reaches_hota():
    gt, pred = moving_tracks(1)
    written = pred.as_written()
    assert score(gt, pred, threshold=4.0)["HOTA"] == pytest.approx(hota(gt, written, threshold=4.0)["HOTA"],
                                                                    abs=1e-12)
    assert score(gt, pred, threshold=4.0)["HOTA"] != pytest.approx(score(gt, pred, threshold=10.0)["HOTA"])


def test_scores_are_those_of_the_written_file(tmp_path):
    """HOTA's similarity thresholds tell 1e-4 px apart: a command's printed scores are eval's on its file."""
    gt, pred = moving_tracks(2)
    path = tmp_path / "tracks.txt"
    path.write_text(format_lines(pred))
    back = read_mot(path)
    assert score(gt, pred, threshold=10.0) == score(gt, back, threshold=10.0)
    assert not np.array_equal(pred.x, back.x)                        # the file does round


def test_ignored_truth_is_scored_as_if_removed_with_the_predictions_on_it():
    gt, pred = moving_tracks(2)
    frames = np.arange(1, 26)
    parked = from_points(frames, np.full(25, 50), np.full(25, 300.0), np.full(25, 300.0))
    on_parked = from_points(frames, np.full(25, 60), np.full(25, 301.0), np.full(25, 299.5))     # 1.1 px away
    beside = from_points(frames[:5], np.full(5, 61), np.full(5, 315.0), np.full(5, 300.0))        # 15 px: not on it
    all_gt = concat_mot([gt, parked])
    all_pred = concat_mot([pred, on_parked, beside])
    ignore = all_gt.id == 50
    kept_gt, kept_pred = gt, concat_mot([pred, beside]).as_written()     # the data with those lines removed

    ours = score(all_gt, all_pred, threshold=10.0, ignore=ignore)
    ref_hota, ref_clear = hota(kept_gt, kept_pred, threshold=10.0), clear_mot(kept_gt, kept_pred, threshold=10.0)
    assert {k: ours[k] for k in HOTA_KEYS} == pytest.approx({k: ref_hota[k] for k in HOTA_KEYS}, abs=1e-12)
    assert {k: ours[k] for k in ("MOTA", "IDF1", "FP", "FN")} == {k: ref_clear[k] for k in ("MOTA", "IDF1", "FP", "FN")}
    assert ours["FP"] == score(gt, pred)["FP"] + 5                       # the 15 px neighbour is a false alarm
    assert score(all_gt, all_pred, threshold=10.0)["HOTA"] != pytest.approx(ours["HOTA"])   # ignoring matters


def test_table1_header_shows_hota_and_idf1_beside_mota():
    m = {"GT": 4, "MT": 1, "PT": 2, "ML": 1, "FP": 3, "FN": 4, "IDS": 1, "MOTA": 0.5, "HOTA": 0.4125,
         "IDF1": 0.6, "MOTP": 1.25, "FPS": 10.0}
    title, header, _, row = format_table1({"x": m}, protocol(True, 10.0)).splitlines()
    assert title == "scored on moving vehicles (the others don't-care), centre distance <= 10.0 px"
    assert protocol(False, 5.0) == "scored on all objects, centre distance <= 5.0 px"
    assert re.split(r"\s{2,}", header.strip()) == TABLE1_HEADER
    assert TABLE1_HEADER[-5:] == ["MOTA (%)", "HOTA (%)", "IDF1 (%)", "MOTP (px)", "FPS"]
    assert row.split()[-5:] == ["50.00", "41.25", "60.00", "1.25", "10.00"]
