"""`torchtrack track --tracker glmb` and `--compare --trackers ... glmb` end to end on a small scene."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_baselines_track_cli import scene

from torchtrack.cli import main
from torchtrack.io.mot import read_mot


@pytest.mark.parametrize("velocities", [True, False])
def test_track_glmb_writes_tracks_and_scores(tmp_path, capsys, velocities):
    gt, det = scene(tmp_path)
    if not velocities:          # the same detections without the detector's velocity columns
        lines = [",".join(line.split(",")[:7] + ["-1", "-1", "-1"]) for line in det.read_text().splitlines()]
        det.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    assert main(["track", "--detections", str(det), "--tracker", "glmb", "--gt", str(gt), "--out", str(out)]) == 0
    tracks = read_mot(out / "tracks.txt")
    m = json.loads((out / "metrics.json").read_text())
    assert m["GT"] == 3 and m["MOTA"] > 0.7 and m["IDS"] <= 1 and "cap_hits" in m
    assert len(np.unique(tracks.id)) == 3                 # one label per vehicle, no clutter track reported
    assert "glmb" in capsys.readouterr().out


def test_compare_includes_glmb(tmp_path, capsys):
    gt, det = scene(tmp_path, seed=1)
    assert main(["track", "--detections", str(det), "--gt", str(gt), "--compare", "--trackers", "labelled-gmphd",
                 "glmb", "--out", str(tmp_path / "cmp"), "--json", str(tmp_path / "cmp.json")]) == 0
    res = json.loads((tmp_path / "cmp.json").read_text())
    assert set(res) == {"labelled-gmphd", "glmb"} and res["glmb"]["MOTA"] > 0.7
