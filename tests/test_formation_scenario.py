"""Formation simulation statistics and the scenario command end to end (tiny sizes)."""

import dataclasses
import json
from pathlib import Path

import pytest
import torch
import yaml

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.scenarios.formation import DEFAULT_CONFIG, load_config
from torchtrack.sim.formation import FormationConfig, simulate_formation


def test_simulation_statistics_and_reproducibility():
    cfg = FormationConfig(num_steps=30, clutter_density=2e-6)
    data = simulate_formation(cfg, 200, torch.Generator().manual_seed(0))
    R, K, N = 200, 30, 4
    assert data.truth.shape == (R, K, N, 4)
    torch.testing.assert_close(data.truth[:, 0, :, 1], torch.tensor([0.0, 200.0, 400.0, 600.0],
                                                                    dtype=torch.float64).expand(R, N))
    assert abs(float(data.truth[..., 2].mean()) - 25.0) < 0.1
    # detection probability and classifier confusion
    det = torch.stack([(data.z_origin == n).any(-1) for n in range(N)], -1)
    assert abs(float(det.double().mean()) - cfg.p_detect) < 0.01
    target = data.z_origin >= 0
    true_cls = data.target_class[data.z_origin.clamp_min(0)]
    right = (data.z_class == true_cls)[target].double().mean()
    assert abs(float(right) - 0.98) < 0.005
    # clutter count: Poisson with mean density x area; clutter classes uniform
    x0, x1, y0, y1 = cfg.region()
    clutter = data.z_origin == -1
    assert abs(float(clutter.sum(-1).double().mean()) - cfg.clutter_density * (x1 - x0) * (y1 - y0)) < 0.1
    assert abs(float((data.z_class[clutter] == 1).double().mean()) - 0.5) < 0.02
    # target measurements scatter with the configured sigma around the truth
    idx = data.z_origin.clamp_min(0).unsqueeze(-1).expand(-1, -1, -1, 2)
    truth_pos = torch.gather(data.truth[..., :2], 2, idx)
    err = (data.z - truth_pos)[target]
    assert abs(float(err.std()) - cfg.measurement_sigma) < 1.0
    again = simulate_formation(cfg, 200, torch.Generator().manual_seed(0))
    assert torch.equal(again.z, data.z) and torch.equal(again.z_class, data.z_class)


def test_config_file_matches_defaults_and_is_checked(tmp_path):
    cfg = load_config(DEFAULT_CONFIG)
    raw = yaml.safe_load(Path(DEFAULT_CONFIG).read_text())["scenario"]
    assert dataclasses.asdict(cfg["scenario"]) == {**raw, "classes": tuple(raw["classes"])}
    assert dataclasses.asdict(FormationConfig()) == dataclasses.asdict(cfg["scenario"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("scenario: {}\n")
    with pytest.raises(TorchtrackError, match=r"missing key\(s\) \[.association., .filter.\]"):
        load_config(bad)


def test_scenario_command_writes_table_json_and_plots(tmp_path, capsys):
    doc = yaml.safe_load(Path(DEFAULT_CONFIG).read_text())
    doc["scenario"]["num_steps"] = 6
    doc["association"]["density_samples"] = 200
    cfg_path = tmp_path / "small.yaml"
    cfg_path.write_text(yaml.safe_dump(doc))
    out = tmp_path / "f.json"
    rc = main(["scenario", "formation", "--runs", "3", "--seed", "1", "--config", str(cfg_path), "--json", str(out),
               "--plot", str(tmp_path / "plots")])
    assert rc == 0
    res = json.loads(out.read_text())
    assert res["runs"] == 3
    for gate in ("rectangular", "ellipsoidal", "class_conditioned"):
        p = res["association_probability"][gate]
        assert set(p) == {"class_1", "class_2"} and all(0.0 <= v <= 1.0 for v in p.values())
        assert res["gate_volume"][gate] > 0
    assert "Table 1" in capsys.readouterr().out
    assert (tmp_path / "plots" / "formation_class_conditioned.png").stat().st_size > 0
    assert main(["scenario", "formation", "--runs", "0", "--config", str(cfg_path)]) == 2
