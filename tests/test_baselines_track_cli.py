"""`torchtrack track`: one tracker, --compare (Table 1), and a short real-data run (skipped without data)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from torchtrack.cli import main
from torchtrack.io.mot import read_mot, write_mot


def scene(tmp_path: Path, T: int = 25, seed: int = 0) -> tuple[Path, Path]:
    rng = np.random.default_rng(seed)
    p0 = np.array([[20.0, 30.0], [100.0, 40.0], [60.0, 150.0]])
    v = np.array([[4.0, 1.0], [-3.0, 2.0], [0.5, -4.0]])
    gf, gi, gx, gy, df, dx, dy, dvx, dvy = ([] for _ in range(9))
    for k in range(1, T + 1):
        pos = p0 + v * k
        for i in range(3):
            gf.append(k), gi.append(i + 1), gx.append(pos[i, 0]), gy.append(pos[i, 1])
            if rng.random() < 0.9:
                z = pos[i] + rng.normal(0, 0.7, 2)
                df.append(k), dx.append(z[0]), dy.append(z[1]), dvx.append(v[i, 0]), dvy.append(v[i, 1])
        for _ in range(rng.poisson(2)):
            df.append(k), dx.append(rng.uniform(0, 200)), dy.append(rng.uniform(0, 200))
            dvx.append(0.0), dvy.append(0.0)
    gt, det = tmp_path / "gt.txt", tmp_path / "det.txt"
    write_mot(gt, gf, gi, gx, gy)
    write_mot(det, df, np.full(len(df), -1), dx, dy, vx=dvx, vy=dvy)
    return gt, det


def test_track_one_tracker_writes_tracks_and_metrics(tmp_path, capsys):
    gt, det = scene(tmp_path)
    out = tmp_path / "out"
    assert main(["track", "--detections", str(det), "--tracker", "gmphd", "--gt", str(gt), "--out", str(out)]) == 0
    tracks = read_mot(out / "tracks.txt")
    assert tracks.size > 50 and set(np.unique(tracks.id)).__len__() >= 3
    m = json.loads((out / "metrics.json").read_text())
    for key in ("MOTA", "MOTP", "IDF1", "MT", "PT", "ML", "FP", "FN", "IDS", "GT", "FPS", "cap_hits"):
        assert key in m
    assert m["GT"] == 3 and m["MOTA"] > 0.7 and m["cap_hits"] == 0
    assert "MOTA (%)" in capsys.readouterr().out


def test_track_compare_prints_table_one(tmp_path, capsys):
    gt, det = scene(tmp_path, seed=1)
    out = tmp_path / "cmp"
    names = ["gmphd", "labelled-gmphd", "sort", "greedy"]
    assert main(["track", "--detections", str(det), "--gt", str(gt), "--compare", "--trackers", *names,
                 "--out", str(out), "--json", str(tmp_path / "cmp.json")]) == 0
    text = capsys.readouterr().out
    for col in ("GT", "MT (%)", "PT (%)", "ML (%)", "FP", "FN", "IDS", "MOTA (%)", "MOTP", "FPS", *names):
        assert col in text
    res = json.loads((tmp_path / "cmp.json").read_text())
    assert set(res) == set(names)
    for n in names:
        assert (out / n / "tracks.txt").exists() and (out / n / "metrics.json").exists()


def test_track_errors(tmp_path, capsys):
    assert main(["track", "--out", str(tmp_path)]) == 2
    assert "give an input: --video FILE, --frames DIR" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("nosuchtracker: {}\n")
    gt, det = scene(tmp_path)
    assert main(["track", "--detections", str(det), "--config", str(bad), "--out", str(tmp_path)]) == 2
    assert "unknown tracker section" in capsys.readouterr().err


def test_gmphd_on_real_wpafb_trajectories_short(wpafb_data, tmp_path):
    """40 frames of real moving vehicles, simulated detections at the benchmark's defaults."""
    from torchtrack.io.moving import moving_mask
    from torchtrack.io.wpafb import read_wpafb_csv
    from torchtrack.pipeline.detection_file import detection_file_config, track_detections
    from torchtrack.sim.detections import simulate_detections

    truth = read_wpafb_csv(wpafb_data / "transformed_object_states.csv")
    truth = truth.select(moving_mask(truth) & (truth.frame <= 40))
    det = simulate_detections(truth, 0.9, 1.0, 30, (585, 496), 1.0, torch.Generator().manual_seed(0)).detections
    m = track_detections(det, "gmphd", detection_file_config(), tmp_path / "out", truth)
    assert m["MOTA"] > 0.6 and m["cap_hits"] == 0
