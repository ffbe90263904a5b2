"""K-fold cross-validation of tune configs (``torchtrack tune --folds K``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml
from test_tune_config import _config as kalman_config
from test_tune_gmphd import draws_config

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.tuning.crossval import cross_validate, fold_config
from torchtrack.tuning.registry import fold_bounds, get_tunable, split_items
from torchtrack.tuning.tune import load_filter


@pytest.mark.parametrize("n, folds", [(10, 3), (512, 4), (7, 7), (5, 2)])
def test_fold_bounds_partition_the_range_into_near_equal_blocks(n, folds):
    bounds = fold_bounds(n, folds)
    assert len(bounds) == folds
    covered = [i for lo, hi in bounds for i in range(lo, hi)]
    assert covered == list(range(n))
    lengths = [hi - lo for lo, hi in bounds]
    assert max(lengths) - min(lengths) <= 1 and min(lengths) >= 1


@pytest.mark.parametrize("folds", [1, 11, 2.5, None])
def test_fold_bounds_refuse_a_bad_number_of_folds(folds):
    with pytest.raises(TorchtrackError, match="folds must be an integer from 2"):
        fold_bounds(10, folds)


def test_item_folds_hold_out_each_item_exactly_once_and_train_on_the_rest():
    items = list("abcdefghij")
    held = []
    for k in range(3):
        data = split_items(items, {"fold": k, "folds": 3}, "data")
        assert sorted(data.train + data.held_out) == items and not set(data.train) & set(data.held_out)
        assert data.train == [i for i in items if i not in data.held_out]   # order kept
        held += data.held_out
    assert held == items
    with pytest.raises(TorchtrackError, match=r"held_out.fold must be an integer from 0 to 2"):
        split_items(items, {"fold": 3, "folds": 3}, "data")
    with pytest.raises(TorchtrackError, match="unknown key"):
        split_items(items, {"fold": 0, "folds": 3, "seed": 1}, "data")


def test_frame_folds_cut_the_configured_frames_into_blocks():
    cfg = yaml.safe_load((Path(__file__).parents[1] / "configs" / "tune-gmphd-wpafb.yaml").read_text())
    original = json.dumps(cfg, sort_keys=True)
    held = []
    for k in range(4):
        data = fold_config(cfg, k, 4)["data"]
        lo, hi = data["held_out_frames"]
        held += list(range(lo, hi + 1))
        train_frames = [f for a, b in data["train_frames"] for f in range(a, b + 1)]
        assert sorted(train_frames + list(range(lo, hi + 1))) == list(range(1, 513))
    assert held == list(range(1, 513))
    assert fold_config(cfg, 1, 4)["data"]["train_frames"] == [[1, 128], [257, 512]]
    assert json.dumps(cfg, sort_keys=True) == original          # the caller's config is not changed
    no_spans = {**cfg, "data": {k: v for k, v in cfg["data"].items() if k != "train_frames"}}
    with pytest.raises(TorchtrackError, match="needs data.train_frames"):
        fold_config(no_spans, 0, 4)


def test_cross_validation_scores_each_fold_s_fit_and_grid_on_its_own_block(tmp_path):
    cfg = draws_config(tmp_path, [5, 6])
    summary = cross_validate(cfg, 2, out=tmp_path / "cv", progress=False)
    assert [r["held_out_frames"] for r in summary["runs"]] == [[1, 20], [21, 40]]
    tun = get_tunable("gmphd", cfg["model"])
    for k, run in enumerate(summary["runs"]):
        assert run["output"]["params"] == str(tmp_path / "cv" / f"fold-{k + 1}" / "params.yaml")
        data = tun.load_data(fold_config(cfg, k, 2)["data"], torch.Generator().manual_seed(0))
        assert [w.frames for w in data.draws[5]] == [list(range(1 + 20 * k, 21 + 20 * k))]
        fitted = load_filter(run["output"]["params"])
        mota = [tun.evaluate(fitted, data.draws[s])["MOTA"] for s in (5, 6)]
        assert summary["per_fold"]["tuned"][k]["MOTA"] == pytest.approx(sum(mota) / 2, abs=1e-12)
    for method in ("tuned", "grid"):
        folds = [f["MOTA"] for f in summary["per_fold"][method]]
        assert summary["mean"][method]["MOTA"] == pytest.approx(sum(folds) / 2, abs=1e-12)
    diff = summary["difference"]
    assert diff["metric"] == "MOTA"
    assert diff["per_fold"] == pytest.approx([t["MOTA"] - g["MOTA"] for t, g in
                                              zip(summary["per_fold"]["tuned"], summary["per_fold"]["grid"])])


def test_tune_command_folds_runs_every_fold_and_writes_the_summary(tmp_path, capsys):
    json_path = tmp_path / "cv.json"
    rc = main(["tune", "--config", str(kalman_config(tmp_path)), "--out", str(tmp_path / "cv"), "--folds", "3",
               "--json", str(json_path), "--no-progress"])
    assert rc == 0
    summary = json.loads(json_path.read_text())
    assert [(r["train_items"], r["held_out_items"]) for r in summary["runs"]] == [(4, 2)] * 3
    assert all((tmp_path / "cv" / f"fold-{k}" / "params.yaml").exists() for k in (1, 2, 3))
    out = capsys.readouterr().out
    assert "3-fold cross-validation" in out and "mean" in out
    assert main(["tune", "--config", str(kalman_config(tmp_path)), "--out", str(tmp_path / "cv9"), "--folds", "9"]) == 2
    assert "folds must be an integer from 2" in capsys.readouterr().err
