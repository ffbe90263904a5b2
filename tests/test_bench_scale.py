"""``torchtrack bench scale``: the constant-density workload, its JSON rows and the time-limit rule."""

import json
import math

import numpy as np

from torchtrack.bench import scale
from torchtrack.cli import main


def test_workload_has_constant_density_and_the_stated_noise():
    scene = scale.simulate(400, 5, seed=3)
    assert math.isclose(scene.side, 60 * 20)                       # 400 vehicles on 1200 x 1200 px
    centres = scene.gt.centers().reshape(5, 400, 2)
    step = np.linalg.norm(centres[1] - centres[0], axis=1)
    assert step.min() >= 2.5 - 1e-9 and step.max() <= 3.5 + 1e-9    # straight lines at 2.5-3.5 px/frame
    assert np.allclose(centres[4] - centres[3], centres[1] - centres[0])
    counts = np.array([z.shape[0] for _, z, _ in scene.detections])
    # 0.9 x 400 detected + 100 clutter per frame, up to binomial noise (sd 6)
    assert np.all(np.abs(counts - 460) < 30)


def test_json_rows_mota_and_time_limit(tmp_path):
    out = tmp_path / "scale.json"
    assert main(["bench", "scale", "--vehicles", "30", "60", "--trackers", "gmphd", "greedy", "--frames", "10",
                 "--json", str(out), "--plot", str(tmp_path / "scale.png")]) == 0
    payload = json.loads(out.read_text())
    rows = {(r["tracker"], r["vehicles"]): r for r in payload["rows"]}
    assert set(rows) == {("gmphd", 30), ("gmphd", 60), ("greedy", 30), ("greedy", 60)}
    for r in rows.values():
        assert r["status"] == "ok" and r["frames_run"] == 10 and r["fps"] > 0
    assert 0.5 <= rows["gmphd", 30]["mota"] <= 1.0
    assert rows["gmphd", 30]["cost_ratio"] == 1.0 and rows["gmphd", 30]["cap_hits"] == 0
    assert rows["greedy", 30]["cap_hits"] is None
    assert payload["unit"] == "vehicle-frames" and payload["reference"] == "gmphd at N=30"
    assert (tmp_path / "scale.png").read_bytes()[:4] == b"\x89PNG"


def test_a_run_over_the_time_limit_stops_and_skips_the_larger_sizes():
    rows = scale.measure([20, 40, 80], ["sort"], frames=5, max_seconds=1e-9)
    assert [r.status for r in rows] == ["over time limit", "skipped", "skipped"]
    assert rows[0].frames_run == 1 and rows[0].mota is None
    assert rows[1].fps is None and rows[2].frames_run == 0
