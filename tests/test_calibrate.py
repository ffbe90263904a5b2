"""torchtrack calibrate: the fitted sensor against the simulating one, the smoother's leave-one-out predictive
against refiltering, the decision rules against closed forms, the commands end to end and their one-line
errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.io.mot import from_points, write_motdata
from torchtrack.sim.detections import simulate_detections
from torchtrack.tuning.calibrate import calibrate_sensor, detection_frames
from torchtrack.tuning.decisions import confirm_frames, gmphd_section, velocity_clutter_density
from torchtrack.tuning.track_smoother import smooth

SIZE = np.array([585.0, 496.0])


def _truth(n: int = 40, frames: int = 80, seed: int = 0):
    """``n`` nearly constant-velocity targets reflected at the image's borders."""
    rng = np.random.default_rng(seed)
    p, v = rng.uniform(0, SIZE, (n, 2)), rng.normal(0, 1, (n, 2))
    fr, ids, xs = [], [], []
    for k in range(1, frames + 1):
        v = v + rng.normal(0, 0.1, (n, 2))
        p = p + v
        fr += [k] * n
        ids += list(range(1, n + 1))
        xs.append(SIZE - np.abs(SIZE - np.mod(p, 2 * SIZE)))
    xs = np.concatenate(xs)
    return from_points(fr, ids, xs[:, 0], xs[:, 1])


def _detections(velocity_sigma: float | None = 2.5, frames: int = 80, seed: int = 0):
    return simulate_detections(_truth(frames=frames), pd=0.7, sigma=2.5, clutter=100, image_size=tuple(SIZE),
                               velocity_sigma=velocity_sigma, generator=torch.Generator().manual_seed(seed)).detections


def test_fit_recovers_the_simulating_sensor():
    data = detection_frames(_detections(frames=150, seed=3))
    cal, _, _ = calibrate_sensor(data, gmphd_section)
    kappa = 100 / (SIZE[0] * SIZE[1])
    assert cal.values["sigma"] == pytest.approx(2.5, rel=0.1)
    assert cal.values["p_detection"] == pytest.approx(0.7, rel=0.1)
    assert cal.values["clutter_density"] == pytest.approx(kappa, rel=0.1)
    assert cal.values["velocity_sigma"] == pytest.approx(2.5, rel=0.1)
    assert cal.values["clutter_velocity_sigma"] == pytest.approx(2.5, rel=0.1)
    assert cal.loglik_after >= cal.loglik_before
    assert all(math.isfinite(cal.stderr[k]) and cal.stderr[k] > 0 for k in ("sigma", "p_detection"))


def test_leave_one_out_predictive_equals_refiltering_without_the_measurement():
    g = torch.Generator().manual_seed(1)
    z = torch.randn(3, 12, 4, generator=g, dtype=torch.float64).cumsum(1)
    z[1, 5] = float("nan")
    q, sigma, vs = 0.7, 1.3, 0.9
    out = smooth(z, q, sigma, vs)
    R = torch.diag(torch.tensor([sigma ** 2] * 2 + [vs ** 2] * 2, dtype=torch.float64))
    for b, t in ((0, 4), (2, 11), (1, 3)):
        cut = z.clone()
        cut[b, t] = float("nan")
        ref = smooth(cut, q, sigma, vs)              # the smoothed state without z_t is the LOO predictive
        torch.testing.assert_close(out.loo_mean[b, t], ref.mean[b, t], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(out.loo_state_cov[b, t], ref.cov[b, t], rtol=1e-5, atol=1e-6)
        assert torch.linalg.eigvalsh(out.loo_state_cov[b, t] + R).min() > 0


def test_decision_rules_closed_form():
    ell = math.log(0.9 / 1e-4) - math.log(2 * math.pi) - 1           # ℓ per frame; n = ceil(log 1e4 / ℓ)
    assert confirm_frames(0.9, 1.0, 1e-4) == math.ceil(math.log(1e4) / ell) == 2
    for pd, sigma, kappa in ((0.7, 2.5, 3.45e-4), (0.6, 4.0, 1e-3)):   # brute force: the first n with n ℓ ≥ log B
        ell = math.log(pd / kappa) - math.log(2 * math.pi * sigma ** 2) - 1
        assert confirm_frames(pd, sigma, kappa) == next(n for n in range(1, 100) if n * ell >= math.log(1e4))
    tau = 2.5                                         # exp E[log N(v; 0, τ²I)] by Monte Carlo
    v = torch.randn(400_000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * tau
    mean_log = float((-0.5 * (v ** 2).sum(1) / tau ** 2 - math.log(2 * math.pi * tau ** 2)).mean())
    assert velocity_clutter_density(tau) == pytest.approx(math.exp(mean_log), rel=5e-3)


def test_calibrate_and_track_calibrate_end_to_end(tmp_path):
    det = tmp_path / "det.txt"
    write_motdata(det, _detections(frames=40))
    out = tmp_path / "cal"
    assert main(["calibrate", "--detections", str(det), "--frames", "1", "30", "--out", str(out)]) == 0
    record = json.loads((out / "calibration.json").read_text())
    assert record["frames"] == [1, 30] and record["velocities"] is True
    assert {"sigma", "p_detection", "clutter_density", "velocity_sigma"} <= set(record["stderr"])
    assert (out / "loss.png").stat().st_size > 0
    from torchtrack.filters.trackers.options import load_tracker_configs
    configs = load_tracker_configs(out / "track.yaml")
    assert set(configs) == {"gmphd", "labelled-gmphd", "glmb", "pmb"}
    assert configs["gmphd"].filter.sigma == pytest.approx(record["values"]["sigma"], rel=1e-3)
    assert configs["pmb"].clutter_rate == pytest.approx(record["values"]["clutter_density"] * np.prod(
        np.diff(np.reshape(record["region"], (2, 2)), axis=0)), rel=1e-3)
    assert main(["track", "--detections", str(det), "--config", str(out / "track.yaml"),
                 "--out", str(tmp_path / "trk")]) == 0
    assert main(["track", "--detections", str(det), "--calibrate", "30", "--out", str(tmp_path / "online")]) == 0
    online = tmp_path / "online"
    assert {"tracks.txt", "track.yaml", "calibration.json", "loss.png"} <= {p.name for p in online.iterdir()}
    assert json.loads((online / "calibration.json").read_text())["frames"] == [1, 30]


def _error(capsys, argv, command="calibrate") -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"torchtrack {command}: error: ")
    return err[0]


def test_bad_input(tmp_path, capsys):
    empty = tmp_path / "empty.txt"
    empty.write_text("")
    assert "no detections" in _error(capsys, ["calibrate", "--detections", str(empty), "--out", str(tmp_path / "a")])
    one = tmp_path / "one.txt"
    dets = _detections(frames=3)
    write_motdata(one, dets.select(dets.frame == 1))
    assert "1 frame" in _error(capsys, ["calibrate", "--detections", str(one), "--out", str(tmp_path / "b")])
    novel = tmp_path / "novel.txt"
    write_motdata(novel, _detections(velocity_sigma=None, frames=5))
    assert "no velocities" in _error(capsys, ["calibrate", "--detections", str(novel), "--velocity", "yes",
                                              "--out", str(tmp_path / "c")])
    assert "--calibrate" in _error(capsys, ["track", "--detections", str(novel), "--calibrate", "3", "--config",
                                            "gmphd", "--out", str(tmp_path / "d")], "track")
    assert not any((tmp_path / x).exists() for x in "abcd")
