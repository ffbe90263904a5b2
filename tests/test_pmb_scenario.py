"""The pedestrian scenario: truth as in the paper's recording, a tiny end-to-end run with JSON and plots."""

from __future__ import annotations

import json

import torch

from torchtrack.cli import main
from torchtrack.scenarios import pedestrian as ped


def test_truth_follows_the_papers_recording():
    cfg = ped.load_config(ped.DEFAULT_CONFIG)
    truth = ped.make_truth(cfg["scene"], cfg["scene"]["steps"])
    present = truth.present[:, 1]
    assert truth.present.shape == (1461, 2) and bool(truth.present[:, 0].all())
    assert int(present.nonzero()[0]) == 208 and int(present.nonzero()[-1]) == 1329
    x = truth.features[:, 1, 0]
    for stop in (10.0, 20.0, 30.0):                       # rests of 200 steps at about 10, 20, 30 m
        assert int(((x - stop).abs() < 1e-9).sum()) >= 200
    assert float(x[1329]) > float(x[1100]) > 30.0            # walks away at the end
    assert abs(float(truth.features[0, 0, 0]) - 50.0) < 1.0  # the static feature at about 50 m
    assert bool((truth.vehicle[:, 2:] == 0).all())            # vehicle standing still


def test_simulated_measurements_have_the_papers_statistics():
    cfg = ped.load_config(ped.DEFAULT_CONFIG)
    scene = cfg["scene"]
    truth = ped.make_truth(scene, 400)
    rec = ped.simulate(scene, truth, 50, torch.Generator().manual_seed(0))
    err = rec.gnss - truth.vehicle[:, None, :2]
    assert abs(float(err.var()) - 0.9216) < 0.03
    n_clutter = rec.mask[..., 2:].sum(-1).float()
    assert abs(float(n_clutter.mean()) - 10.0) < 0.1
    det = rec.mask[:, :, 0].float().mean()
    assert abs(float(det) - 0.9) < 0.01


def test_tiny_run_writes_the_json_keys_and_plots(tmp_path):
    out = tmp_path / "ped.json"
    rc = main(["scenario", "pedestrian", "--runs", "2", "--steps", "60", "--seed", "1", "--json", str(out),
               "--plot", str(tmp_path / "plots")])
    assert rc == 0
    payload = json.loads(out.read_text())
    assert set(payload["mean_ospa"]) == {"joint", "inflated", "naive"}
    assert payload["runs"] == 2
    for v in ("joint", "inflated", "naive"):
        per_step = payload["ospa_per_step"][v]
        assert len(per_step) == 60
        assert all(0.0 <= o <= 20.0 for o in per_step)
        assert abs(sum(per_step) / 60 - payload["mean_ospa"][v]) < 1e-9
    assert set(payload["extra_mean_ospa"]) == {"inflated_kf"}
    assert len(payload["extra_ospa_per_step"]["inflated_kf"]) == 60
    assert (tmp_path / "plots" / "pedestrian_ospa.png").is_file()
    assert (tmp_path / "plots" / "pedestrian_positions_joint.png").is_file()
