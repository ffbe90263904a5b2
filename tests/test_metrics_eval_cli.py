"""``torchtrack eval`` and don't-care (ignored) ground truth."""

import json
from pathlib import Path

import numpy as np
import pytest

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points, read_mot, write_motdata
from torchtrack.metrics import clear_mot, hota
from torchtrack.metrics.clear_mot import KEYS
from torchtrack.metrics.hota import KEYS as HOTA_KEYS

mm = pytest.importorskip("motmetrics")
TUD = Path(mm.__file__).parent / "data" / "TUD-Campus"


def test_eval_cli_table_and_json(tmp_path, capsys):
    js = tmp_path / "e.json"
    assert main(["eval", "--gt", str(TUD / "gt.txt"), "--pred", str(TUD / "test.txt"), "--iou", "0.5",
                 "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "MOTA%" in out and "IDF1%" in out
    got = json.loads(js.read_text())
    assert set(KEYS) <= set(got)
    ref = clear_mot(read_mot(TUD / "gt.txt"), read_mot(TUD / "test.txt"), iou=0.5)
    assert {k: got[k] for k in KEYS} == pytest.approx({k: ref[k] for k in KEYS})
    assert f"{100 * ref['MOTA']:.2f}" in out
    ref_hota = hota(read_mot(TUD / "gt.txt"), read_mot(TUD / "test.txt"), iou=0.5)
    assert {k: got[k] for k in HOTA_KEYS} == pytest.approx({k: ref_hota[k] for k in HOTA_KEYS}, abs=1e-12)
    assert "HOTA%" in out and f"{100 * ref_hota['HOTA']:.2f}" in out


def test_eval_cli_bad_file_exits_2_naming_the_line(tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("1,1,1,1,1,1\n2,x,1,1,1,1\n")
    assert main(["eval", "--gt", str(TUD / "gt.txt"), "--pred", str(bad)]) == 2
    assert f"{bad}:2:" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["eval", "--gt", "a", "--pred", "b", "--iou", "0.5", "--threshold", "3"])


def test_ignored_objects_and_their_predictions_are_dropped():
    # frame 1: object 1 (scored) and object 2 (ignored); predictions near each, plus one far away
    gt = from_points([1, 1], [1, 2], [0.0, 100.0], [0.0, 0.0])
    pred = from_points([1, 1, 1], [10, 20, 30], [1.0, 101.0, 300.0], [0.0, 0.0, 0.0])
    r = clear_mot(gt, pred, ignore=np.array([False, True]))
    assert (r["TP"], r["FP"], r["FN"], r["GT"], r["predictions"]) == (1, 1, 0, 1, 2)
    full = clear_mot(gt, pred)
    assert (full["TP"], full["FP"], full["GT"]) == (2, 1, 2)
    with pytest.raises(TorchtrackError, match="ignore"):
        clear_mot(gt, pred, ignore=np.array([True]))


def test_eval_cli_moving_only(tmp_path, capsys):
    # object 1 drives 2 px/frame, object 2 is parked; the tracker follows both
    k = np.arange(1, 31)
    gt = from_points(np.r_[k, k], np.r_[np.ones(30, int), 2 * np.ones(30, int)],
                     np.r_[2.0 * k, np.full(30, 200.0)], np.r_[np.zeros(30), np.full(30, 50.0)])
    write_motdata(tmp_path / "gt.txt", gt)
    write_motdata(tmp_path / "pred.txt", gt._replace(id=gt.id + 10))
    js = tmp_path / "m.json"
    assert main(["eval", "--gt", str(tmp_path / "gt.txt"), "--pred", str(tmp_path / "pred.txt"),
                 "--moving", "--json", str(js)]) == 0
    got = json.loads(js.read_text())
    # moving from frame 4 on (6 px > 5 over the window): 27 lines of object 1 scored, none of object 2
    assert (got["GT"], got["GT_objects"], got["FP"], got["TP"], got["MOTA"]) == (1, 27, 0, 27, 1.0)
    assert got["moving_only"] is True


def test_eval_cli_ospa(tmp_path):
    js = tmp_path / "o.json"
    assert main(["eval", "--gt", str(TUD / "gt.txt"), "--pred", str(TUD / "test.txt"), "--ospa", "50",
                 "--json", str(js)]) == 0
    got = json.loads(js.read_text())
    assert 0 < got["OSPA"] <= 50 and got["GOSPA"] > 0
    assert got["OSPA_cardinality"] > 0 and got["GOSPA_missed"] > 0  # the tracker misses people
