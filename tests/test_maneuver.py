"""Chi-square maneuver detection with two-point reset (the maneuver paper)."""

import json
import math

import pytest
import torch

from torchtrack import TorchtrackError
from torchtrack.cli import main
from torchtrack.filters.kalman.filter import KalmanFilter
from torchtrack.filters.kalman.maneuver import ManeuverDetectingKalmanFilter, two_point_init
from torchtrack.gaussian import chi2_quantile
from torchtrack.models import ConstantVelocity, LinearPosition
from torchtrack.sim.maneuver import maneuvering


def test_chi2_threshold_matches_the_paper():
    # the paper: threshold 10 "corresponds to a probability of 0.99" for 2 degrees of freedom
    assert chi2_quantile(0.99, 2) == pytest.approx(-2 * math.log(0.01))
    assert chi2_quantile(0.99, 2) < 10 < chi2_quantile(0.995, 2)
    with pytest.raises(TorchtrackError, match="probability"):
        chi2_quantile(1.5, 2)


def test_two_point_init_is_differencing():
    R = torch.eye(2, dtype=torch.float64) * 4
    s = two_point_init(torch.tensor([1.0, 2.0], dtype=torch.float64), torch.tensor([3.0, 6.0], dtype=torch.float64),
                       R, 2.0)
    torch.testing.assert_close(s.mean, torch.tensor([3.0, 6.0, 1.0, 2.0], dtype=torch.float64))
    assert s.cov[0, 0] == 4 and s.cov[0, 2] == 2 and s.cov[2, 2] == 2


def _filters(threshold=10.0):
    kf = KalmanFilter(ConstantVelocity(2, q=1e-4, noise="pwca"), LinearPosition(2, sigma=1.0)).double()
    return (ManeuverDetectingKalmanFilter(kf, threshold), ManeuverDetectingKalmanFilter(kf, threshold, reset=False))


def test_detects_each_maneuver_and_resets_independently_per_run():
    gen = torch.Generator().manual_seed(0)
    runs = 40
    seq = maneuvering(100, runs, 10.0, [40], [90.0], 3, 1.0, 0.01, 1.0, gen)
    straight = maneuvering(100, runs, 10.0, [], [], 3, 1.0, 0.01, 1.0, gen)
    z = torch.cat([seq.measurements, straight.measurements], 1)  # first half maneuvers, second half not
    detecting, plain = _filters()
    with torch.no_grad():
        res = detecting.run(z)
        ref = plain.run(z)
    near = res.detected[40:44]
    assert near[:, :runs].any(0).double().mean() >= 0.95
    assert near[:, runs:].any(0).double().mean() <= 0.1
    # resets do not leak between runs: the straight-line runs are filtered exactly as without reset
    # wherever they raised no alarm
    clean = ~res.detected[:, runs:].any(0)
    torch.testing.assert_close(res.mean[:, runs:][:, clean], ref.mean[:, runs:][:, clean])
    err_det = (res.mean[40:55, :runs, :2] - seq.truth[40:55, :, :2]).norm(dim=-1).mean()
    err_kf = (ref.mean[40:55, :runs, :2] - seq.truth[40:55, :, :2]).norm(dim=-1).mean()
    assert err_det < 0.7 * err_kf


def test_false_alarm_rate_matches_the_chi_square_tail():
    gen = torch.Generator().manual_seed(1)
    seq = maneuvering(200, 200, 10.0, [], [], 3, 1.0, 0.0001, 1.0, gen)
    detecting, _ = _filters(threshold=chi2_quantile(0.95, 2))
    with torch.no_grad():
        res = detecting.run(seq.measurements)
    rate = res.detected[20:].double().mean()
    assert 0.03 < rate < 0.08  # nominal 0.05


def test_bad_input():
    detecting, _ = _filters()
    with pytest.raises(TorchtrackError, match="at least 2 scans"):
        detecting.run(torch.zeros(1, 3, 2, dtype=torch.float64))
    z = torch.zeros(5, 3, 2, dtype=torch.float64)
    z[2, 1, 0] = float("nan")
    with pytest.raises(TorchtrackError, match="missing"):
        detecting.run(z)
    kf = KalmanFilter(ConstantVelocity(2), LinearPosition(2, state_dim=4))
    with pytest.raises(TorchtrackError, match="threshold must be > 0"):
        ManeuverDetectingKalmanFilter(kf, threshold=-1.0)


def test_scenario_command_writes_json_and_plots(tmp_path, capsys):
    out = tmp_path / "res.json"
    assert main(["scenario", "maneuver", "--runs", "20", "--seed", "3", "--json", str(out),
                 "--plot", str(tmp_path / "plots")]) == 0
    data = json.loads(out.read_text())
    for key in ("maneuver_onsets", "detection_rate", "median_detection_delay", "false_alarms_per_100_scans",
                "rmse_position_kf", "rmse_position_detecting_kf", "runs"):
        assert key in data
    assert data["maneuver_onsets"] == [60, 125] and data["runs"] == 20
    assert min(data["detection_rate"]) >= 0.9
    assert data["rmse_position_detecting_kf"] < 0.7 * data["rmse_position_kf"]
    assert (tmp_path / "plots" / "maneuver.png").stat().st_size > 10_000
    assert "false alarms per 100 scans" in capsys.readouterr().out
    assert torch.get_default_dtype() == torch.float32  # the command leaves global state alone


def test_scenario_rejects_bad_arguments(capsys):
    assert main(["scenario", "maneuver", "--runs", "0"]) == 2
    assert "--runs must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:                  # argparse's usage error: exit status 2
        main(["scenario", "maneuver", "--config", "/nonexistent.yaml"])
    assert exc.value.code == 2
    assert "argument --config: /nonexistent.yaml: no such file or preset" in capsys.readouterr().err
