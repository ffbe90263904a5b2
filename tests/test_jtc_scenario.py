"""The JTC paper's test trajectory and the ``torchtrack scenario jtc`` command."""

from __future__ import annotations

import json
import math

import torch

from torchtrack.cli import main
from torchtrack.models import RangeBearing
from torchtrack.sim.jtc_trajectory import G, jtc_trajectory, simulate_measurements, true_modes


def _heading(v: torch.Tensor) -> torch.Tensor:
    return torch.atan2(v[..., 1], v[..., 0])


def test_trajectory_speeds_and_turns():
    traj = jtc_trajectory()
    speed = traj.states[:, 2:].norm(dim=-1)
    assert torch.allclose(speed[:45], torch.full((45,), 250.0, dtype=torch.float64), rtol=1e-5)
    # 1g for 15 s: 250 → 397 m/s ("up to 400 m/s"), then constant
    assert abs(speed[47].item() - (250 + 15 * G)) < 0.5 and torch.allclose(speed[47:], speed[47].expand(34))
    # a 2g coordinated turn over scans 16–23 turns by a_n / v · 40 s (counter-clockwise)
    turn = _heading(traj.states[23, 2:]) - _heading(traj.states[15, 2:])
    expected = 2 * G / 250 * 40
    assert abs(math.remainder(turn.item() - expected, 2 * math.pi)) < 1e-3
    # −5g over scans 35–37 (clockwise)
    turn = _heading(traj.states[37, 2:]) - _heading(traj.states[34, 2:])
    assert abs(math.remainder(turn.item() + 5 * G / 250 * 15, 2 * math.pi)) < 1e-3
    # the target stays well away from the radar at the origin
    assert traj.states[:, :2].norm(dim=-1).min() > 10_000


def test_true_modes_and_measurements():
    traj = jtc_trajectory()
    modes = true_modes(traj)
    on = torch.zeros(80, dtype=torch.bool)
    for a, b in ((16, 23), (35, 37), (45, 56), (63, 70)):
        on[a - 1:b] = True
    assert torch.equal(traj.maneuvering, on)
    assert (modes[~on] == 0).all() and (modes[on] > 0).all()
    radar = RangeBearing((0.0, 0.0), 100.0, math.radians(0.15)).double()
    z = simulate_measurements(traj, radar, 2000, torch.Generator().manual_seed(0))
    err = z - radar.measure(traj.states[1:]).unsqueeze(1)
    assert abs(err[..., 0].std().item() / 100.0 - 1) < 0.02
    assert abs(err[..., 1].std().item() / math.radians(0.15) - 1) < 0.02


def test_scenario_command_writes_the_json(tmp_path, capsys):
    out = tmp_path / "jtc.json"
    code = main(["scenario", "jtc", "--runs", "2", "--particles", "100", "--timing-repeats", "1",
                 "--seed", "3", "--json", str(out), "--plot", str(tmp_path / "plots")])
    assert code == 0
    data = json.loads(out.read_text())
    for key in ("class_probability_correct", "rmse_position", "rmse_speed", "mode_probability_correct"):
        assert len(data[key]) == 80 and all(0 <= v for v in data[key])
    assert all(v <= 1 + 1e-6 for v in data["class_probability_correct"] + data["mode_probability_correct"])
    assert data["speed_constraints"] is True and data["runs"] == 2
    assert data["time_per_update_ms"] > 0 and data["time_per_scan_all_runs_ms"] > 0
    assert len(list((tmp_path / "plots").glob("*.png"))) == 3
    assert "time per update" in capsys.readouterr().out


def test_scenario_rejects_bad_counts(capsys):
    assert main(["scenario", "jtc", "--runs", "0"]) == 2
    assert main(["scenario", "jtc", "--runs", "1", "--particles", "0"]) == 2
    assert "num_particles" in capsys.readouterr().err
