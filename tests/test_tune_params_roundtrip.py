"""Fitted-parameter files in the commands: ``torchtrack track --params`` and ``torchtrack scenario
{maneuver, formation} --params`` reproduce the fitted filter's output exactly; other scenarios and
mismatched files are rejected with a clear message."""

import json

import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points, read_mot, write_motdata
from torchtrack.tuning.parameters import get_raw, set_values
from torchtrack.tuning.tune import get_tunable, save_params

AREA = 200.0 * 200.0


def detections_file(tmp_path, frames=25, targets=5, seed=0):
    """Straight-line targets, detected with p_D 0.9, sigma 1 px and 3 clutter points per frame."""
    from torchtrack.sim.detections import simulate_detections

    g = np.random.default_rng(seed)
    pos, vel = g.uniform(40, 160, (targets, 2)), g.normal(0, 1.5, (targets, 2))
    f = np.repeat(np.arange(1, frames + 1), targets)
    i = np.tile(np.arange(1, targets + 1), frames)
    p = pos[None] + vel[None] * np.arange(frames)[:, None, None]
    truth = from_points(f, i, p[..., 0].reshape(-1), p[..., 1].reshape(-1))
    det = simulate_detections(truth, 0.9, 1.0, 3.0, (200, 200), None, torch.Generator().manual_seed(seed)).detections
    path = tmp_path / "det.txt"
    write_motdata(path, det)
    return path


def fitted_gmphd(tmp_path, tracker="labelled-gmphd"):
    """A GM-PHD tracker with off-default values (as a fit leaves them) and its fitted-parameter file."""
    model = {"tracker": tracker, "dtype": "float64",
             "filter": {"p_detection": 0.8, "clutter_density": 3.0 / AREA, "area": AREA, "sigma": 1.0, "q": 0.2}}
    tun = get_tunable("gmphd", model)
    module = tun.build()
    set_values(module, {"phd.p_detection": 0.8731, "phd.clutter_density": 2.345 / AREA, "phd.motion.q": 0.173,
                        "phd.measurement.sigma": 1.137, "birth.birth_weight": 0.0871})
    return module, save_params(module, tmp_path / "params.yaml", "gmphd", model)


def test_track_params_reproduces_the_fitted_tracker_exactly(tmp_path):
    import argparse

    from torchtrack.cli.track import fitted_tracker
    from torchtrack.pipeline.detection_file import detection_file_config
    from torchtrack.pipeline.frame_detections import mot_frames, stream_frames
    from torchtrack.pipeline.replay import run_tracker

    det_path = detections_file(tmp_path)
    module, params = fitted_gmphd(tmp_path)
    det = read_mot(det_path)
    # the tracker --params builds streams exactly the fitted tracker's output
    args = argparse.Namespace(params=params, tracker="labelled-gmphd", config=None, compare=False, benchmark=None,
                              video=None, frames=None, sequences=None)
    loaded = fitted_tracker(args)
    module.reset()
    steps = 0
    for f in mot_frames(det, stream_frames(det)):
        z, v = torch.from_numpy(f.positions), None if np.isnan(f.velocities).any() else torch.from_numpy(f.velocities)
        (ia, pa), (ib, pb) = module.step(f.index, z, v), loaded.step(f.index, z, v)
        assert torch.equal(ia, ib) and torch.equal(pa, pb)
        steps += int(ia.numel())
    assert steps > 20
    # and the command writes the same tracks file
    module.reset()
    run_tracker(module, detection_file_config(), mot_frames(det, stream_frames(det)), tmp_path / "expected.txt")
    out = tmp_path / "out"
    assert main(["track", "--detections", str(det_path), "--params", str(params), "--tracker", "labelled-gmphd",
                 "--out", str(out)]) == 0
    assert (out / "tracks.txt").read_text() == (tmp_path / "expected.txt").read_text()


def test_track_params_rejects_a_mismatched_tracker_or_config(tmp_path, capsys):
    det_path = detections_file(tmp_path, frames=5)
    _, params = fitted_gmphd(tmp_path)
    assert main(["track", "--detections", str(det_path), "--params", str(params), "--out", str(tmp_path)]) == 2
    assert "fitted for --tracker labelled-gmphd" in capsys.readouterr().err
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("gmphd: {}\n")
    assert main(["track", "--detections", str(det_path), "--params", str(params), "--tracker", "labelled-gmphd",
                 "--config", str(cfg), "--out", str(tmp_path)]) == 2
    assert "does not combine with --config" in capsys.readouterr().err


def fitted_kalman_file(tmp_path, noise="pwca"):
    model = {"ndim": 2, "motion": "cv", "noise": noise, "q": 1e-4, "sigma": 1.0, "dtype": "float64"}
    tun = get_tunable("kalman", model)
    kf = tun.build()
    set_values(kf, {"motion.q": 3.21e-3, "measurement.sigma": 0.873})
    return kf, save_params(kf, tmp_path / f"kalman-{noise}.yaml", "kalman", model)


def test_scenario_maneuver_params_reproduce_the_fitted_filter_exactly(tmp_path):
    from torchtrack.filters.kalman.maneuver import ManeuverDetectingKalmanFilter
    from torchtrack.scenarios.maneuver import DEFAULT_CONFIG, fitted_kalman, load_config

    kf, params = fitted_kalman_file(tmp_path)
    fcfg = load_config(DEFAULT_CONFIG)["filter"]
    loaded = fitted_kalman(fcfg, 1.0, params)
    assert all(torch.equal(get_raw(loaded)[n], r) for n, r in get_raw(kf).items())
    z = torch.cumsum(torch.randn(40, 3, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64), 0)
    a = ManeuverDetectingKalmanFilter(kf, threshold=10.0).run(z, 1.0)
    b = ManeuverDetectingKalmanFilter(loaded, threshold=10.0).run(z, 1.0)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
    out = tmp_path / "m.json"
    assert main(["scenario", "maneuver", "--runs", "2", "--params", str(params), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["params"] == str(params)


def test_scenario_maneuver_rejects_a_filter_fitted_with_another_noise_model(tmp_path, capsys):
    _, params = fitted_kalman_file(tmp_path, noise="cwna")
    assert main(["scenario", "maneuver", "--runs", "2", "--params", str(params)]) == 2
    assert "noise': 'cwna'" in capsys.readouterr().err


def test_scenario_formation_params_reproduce_the_fitted_imm_exactly(tmp_path):
    from torchtrack.scenarios.formation import DEFAULT_CONFIG, build_bank, load_config

    model = {"dtype": "float64", "sigma": [0.2, 0.2, 0.2], "measurement_sigma": 55.0}
    tun = get_tunable("imm", model)
    imm = tun.build()
    set_values(imm, {"transition.learned": torch.tensor([[0.9, 0.07, 0.03], [0.2, 0.7, 0.1], [0.05, 0.05, 0.9]]),
                     "motion.sigma": torch.tensor([0.3, 0.25, 0.4]), "measurement.sigma": 61.5})
    params = save_params(imm, tmp_path / "imm.yaml", "imm", model)
    cfg = load_config(DEFAULT_CONFIG)
    bank = build_bank(cfg["filter"], cfg["scenario"].measurement_sigma, cfg["scenario"].confusion, params)
    for c in range(len(bank.imms)):   # every class takes the fitted values, bit for bit
        assert all(torch.equal(get_raw(bank.imms[c])[n], r) for n, r in get_raw(imm).items())
    # class 1 has the tuned model set {0, 3g, -g} along y: its filter output equals the fitted IMM's
    g = torch.Generator().manual_seed(0)
    mean = torch.tensor([[0.0, 0.0, 25.0, 0.0]], dtype=torch.float64)
    cov = torch.diag(torch.tensor([55.0**2, 55.0**2, 100.0, 100.0], dtype=torch.float64))[None]
    sa, sb = imm.initial_state(mean, cov), bank.imms[0].initial_state(mean, cov)
    for k in range(10):
        z = torch.tensor([[25.0 * (k + 1), 0.0]], dtype=torch.float64) + 50 * torch.randn(1, 2, generator=g,
                                                                                           dtype=torch.float64)
        sa, _ = imm.update(imm.predict(sa, 1.0), z)
        sb, _ = bank.imms[0].update(bank.imms[0].predict(sb, 1.0), z)
    for x, y in zip(sa, sb):
        assert torch.equal(x, y)


def test_scenario_formation_rejects_other_filters(tmp_path):
    from torchtrack.scenarios.formation import DEFAULT_CONFIG, build_bank, load_config

    _, params = fitted_kalman_file(tmp_path)
    cfg = load_config(DEFAULT_CONFIG)
    with pytest.raises(TorchtrackError, match="takes those of 'imm'"):
        build_bank(cfg["filter"], 55.0, cfg["scenario"].confusion, params)


@pytest.mark.parametrize("scenario", ["jtc", "pedestrian"])
def test_scenarios_without_a_tunable_filter_refuse_params(tmp_path, scenario, capsys):
    _, params = fitted_kalman_file(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["scenario", scenario, "--params", str(params)])
    assert exc.value.code == 2
    assert "formation (imm), maneuver (kalman)" in capsys.readouterr().err
