"""Fitted-parameter files: exact round-trip, hand edits, bad files; the tune command end to end."""

import json
from pathlib import Path

import pytest
import torch
import yaml

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.tuning.parameters import get_raw
from torchtrack.tuning.tune import fit, get_tunable, get_values, load_filter, load_params, save_params


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_written_config_reproduces_the_fitted_filter_exactly(tmp_path, dtype):
    tun = get_tunable("kalman", {"q": 3.0, "sigma": 6.0, "dtype": dtype})
    kf = tun.build()
    data = tun.load_data({"simulate": {"sequences": 4, "steps": 20, "q": 1.0, "sigma": 2.0}},
                         torch.Generator().manual_seed(0))
    fit(tun, kf, ["motion.q", "measurement.sigma"], data, "nll", {"name": "adam", "lr": 0.3, "steps": 5},
        progress=False)
    path = save_params(kf, tmp_path / "params.yaml", "kalman", tun.options)
    fresh = load_filter(path)
    assert type(fresh) is type(kf)
    with torch.no_grad():
        a, _, _ = tun.filter(kf, data.train)
        b, _, _ = tun.filter(fresh, data.train)
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    # the same through load_params into a module built separately
    other = get_tunable("kalman", {"q": 7.0, "sigma": 1.0, "dtype": dtype}).build()
    load_params(other, path)
    assert all(torch.equal(get_raw(other)[n], v) for n, v in get_raw(kf).items())
    doc = yaml.safe_load(path.read_text())
    assert doc["filter"] == "kalman" and set(doc["params"]) == {"motion.q", "measurement.sigma"}
    assert doc["params"]["motion.q"] == pytest.approx(get_values(kf)["motion.q"].item(), rel=1e-7)


def test_hand_edited_value_wins_over_stale_raw(tmp_path):
    kf = get_tunable("kalman", {"q": 2.0, "sigma": 3.0}).build()
    path = save_params(kf, tmp_path / "p.yaml", "kalman", {"q": 2.0, "sigma": 3.0})
    doc = yaml.safe_load(path.read_text())
    doc["params"]["measurement.sigma"] = 4.5
    del doc["raw"]["motion.q"]
    path.write_text(yaml.safe_dump(doc))
    fresh = load_filter(path)
    values = get_values(fresh)
    assert values["measurement.sigma"].item() == pytest.approx(4.5, rel=1e-12)
    assert values["motion.q"].item() == pytest.approx(doc["params"]["motion.q"], rel=1e-12)


def test_bad_parameter_files(tmp_path):
    kf = get_tunable("kalman").build()
    bad = tmp_path / "bad.yaml"
    bad.write_text("filter: kalman\nparams: {motion.qq: 1.0}\n")
    with pytest.raises(TorchtrackError, match=r"unknown parameter\(s\) 'motion.qq'.*valid names: measurement.sigma"):
        load_params(kf, bad)
    bad.write_text("filter: kalman\nparams: {motion.q: -1.0}\n")
    with pytest.raises(TorchtrackError, match="must be > 0"):
        load_params(kf, bad)
    bad.write_text("filter: kalman\nparams: {motion.q: [1.0, 2.0]}\n")
    with pytest.raises(TorchtrackError, match="shape"):
        load_params(kf, bad)
    bad.write_text("filter: nofilter\nparams: {motion.q: 1.0}\n")
    with pytest.raises(TorchtrackError, match="unknown filter 'nofilter'"):
        load_filter(bad)
    bad.write_text("filter: kalman\nparams: [\n")
    with pytest.raises(TorchtrackError, match="bad.yaml"):
        load_params(kf, bad)


def _config(tmp_path, **overrides):
    cfg = {"filter": "kalman", "model": {"q": 3.0, "sigma": 6.0, "dtype": "float64"},
           "trainable": ["motion.q", "measurement.sigma"],
           "data": {"simulate": {"sequences": 6, "steps": 20, "q": 1.0, "sigma": 2.0}, "held_out": 2},
           "optimizer": {"name": "lbfgs", "steps": 2, "max_iter": 5}, "seed": 1}
    cfg.update(overrides)
    path = tmp_path / "tune.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_tune_command_writes_params_plot_and_json(tmp_path, capsys):
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    rc = main(["tune", "--config", str(cfg), "--out", str(out), "--json", str(tmp_path / "r.json"), "--no-progress"])
    assert rc == 0
    assert (out / "params.yaml").exists() and (out / "loss.png").stat().st_size > 1000
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["truth"] == {"motion.q": 1.0, "measurement.sigma": 2.0}
    assert report["held_out_after"]["loss"] < report["held_out_before"]["loss"]
    fitted = load_filter(out / "params.yaml")
    assert get_values(fitted)["motion.q"].item() == pytest.approx(report["fitted"]["motion.q"], rel=1e-12)
    assert "motion.q" in capsys.readouterr().out


def test_tune_command_reports_bad_configs(tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main(["tune", "--config", str(_config(tmp_path, trainable=["motion.x"])), "--out", out]) == 2
    assert "valid names: measurement.sigma, motion.q" in capsys.readouterr().err
    assert main(["tune", "--config", str(_config(tmp_path, optimiser={})), "--out", out]) == 2
    assert "unknown key(s) ['optimiser']" in capsys.readouterr().err
    assert main(["tune", "--config", str(_config(tmp_path, loss="mse")), "--out", out]) == 2
    assert "unknown loss 'mse'" in capsys.readouterr().err


def test_tune_command_set_overrides_config_entries(tmp_path, capsys):
    json_path = tmp_path / "r.json"
    rc = main(["tune", "--config", str(_config(tmp_path)), "--out", str(tmp_path / "out"), "--json", str(json_path),
               "--no-progress", "--set", "data.held_out=3", "--set", "seed=2", "--set", "early_stopping.patience=1",
               "--set", "trainable=motion.q"])
    assert rc == 0
    report = json.loads(json_path.read_text())
    assert report["held_out_items"] == 3 and report["train_items"] == 3 and report["seed"] == 2
    assert report["trainable"] == ["motion.q"] and set(report["fitted"]) == {"motion.q"}


@pytest.mark.parametrize("assignment, message", [
    ("data.held_out", "expected KEY=VALUE"),
    ("data..held_out=2", "expected KEY=VALUE"),
    ("dataset.held_out=2", "unknown key 'dataset'"),
    ("data.held_out=[1", "invalid YAML value"),
    ("seed.x=1", "'seed' is not a mapping"),
])
def test_tune_command_set_refuses_bad_assignments(tmp_path, capsys, assignment, message):
    assert main(["tune", "--config", str(_config(tmp_path)), "--out", str(tmp_path), "--set", assignment]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("path", sorted((Path(__file__).resolve().parents[1] / "configs")
                                        .glob("tune-*.yaml")), ids=lambda p: p.name)
def test_shipped_tune_configs_are_valid(path):
    from torchtrack.tuning.config import read_tune_config
    from torchtrack.tuning.parameters import select_trainable

    cfg = read_tune_config(path)
    tun = get_tunable(cfg["filter"], cfg.get("model") or {})
    select_trainable(tun.build(), cfg["trainable"])
    assert (cfg.get("loss") or tun.losses[0]) in tun.losses
