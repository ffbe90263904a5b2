"""``torchtrack bench calibrate`` end to end on a small synthetic scene: the JSON holds the held-out scores of the
calibration, the built-in options and (with Optuna) the reference, for the GM-PHD, the GLMB and the PMB, and the
scores are those of ``torchtrack.track`` with the same options."""

from __future__ import annotations

import importlib.util
import json

import pytest
import torch
from test_calibrate import SIZE, _truth

import torchtrack
from torchtrack.cli import main
from torchtrack.io.mot import write_motdata
from torchtrack.sim.detections import simulate_detections


def test_bench_calibrate_reports_every_configuration(tmp_path, capsys):
    gt = tmp_path / "gt.txt"
    truth = _truth(n=30, frames=60, seed=4)
    write_motdata(gt, truth)
    out = tmp_path / "bench.json"
    assert main(["bench", "calibrate", "--gt", str(gt), "--pd", "0.8", "--sigma", "1.5", "--clutter", "40",
                 "--velocity-sigma", "1.5", "--image-size", *map(str, SIZE), "--train", "1", "45", "--test", "46",
                 "60", "--trials", "2", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    printed = capsys.readouterr().out
    assert report["status"] in ("ok", "retried", "defaults") and f"calibration status: {report['status']}" in printed
    assert set(report["others_mota"]) == {"glmb", "pmb"}
    has_optuna = importlib.util.find_spec("optuna") is not None
    assert (report["reference_mota"] is not None) == has_optuna
    det = simulate_detections(truth, 0.8, 1.5, 40, tuple(SIZE), 1.5, torch.Generator().manual_seed(0)).detections
    test = det.select(det.frame >= 46)
    built_in = torchtrack.track(detections=test, gt=truth.select(truth.frame >= 46), score="all")
    assert report["defaults_mota"] == pytest.approx(built_in.metrics["MOTA"])
