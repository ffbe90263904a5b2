"""Simulated detections: statistics of misses, noise, clutter and velocities; determinism; the CLI."""

import json

import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points, read_mot, write_motdata
from torchtrack.sim.detections import default_image_size, simulate_detections, truth_velocity


def moving_truth(frames=200, objects=50, seed=0):
    """Objects on straight lines with known velocities; every 4th object skips a few frames."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(100, 300, (objects, 2))
    vel = rng.uniform(-3, 3, (objects, 2))
    k = np.arange(1, frames + 1)
    fr = np.repeat(k, objects)
    ids = np.tile(np.arange(objects), frames)
    pos = start[ids] + vel[ids] * (fr[:, None] - 1)
    keep = ~((ids % 4 == 0) & (fr % 10 < 3))
    return from_points(fr[keep], ids[keep], pos[keep, 0], pos[keep, 1]), vel


def test_statistics_match_the_model():
    truth, vel = moving_truth()
    gen = torch.Generator().manual_seed(3)
    sim = simulate_detections(truth, pd=0.8, sigma=2.0, clutter=5.0, image_size=(400, 300),
                              velocity_sigma=0.5, generator=gen)
    det, src = sim.detections, sim.source
    true = src >= 0
    n = truth.size
    assert abs(true.sum() / n - 0.8) < 4 * np.sqrt(0.8 * 0.2 / n)
    frames = truth.frames().size
    assert abs((~true).sum() / frames - 5.0) < 4 * np.sqrt(5.0 / frames)
    np.testing.assert_array_equal(det.id, -1)
    assert np.all(np.diff(det.frame) >= 0)
    # position noise: match each true detection back to its truth line
    lookup = {(f, i): c for f, i, c in zip(truth.frame, truth.id, truth.centers())}
    err = det.centers()[true] - np.array([lookup[(f, i)] for f, i in zip(det.frame[true], src[true])])
    assert abs(err.mean()) < 0.05 and abs(err.std() - 2.0) < 0.05
    # velocity = the object's constant velocity + N(0, 0.5^2)
    verr = det.velocity()[true] - vel[src[true]]
    assert abs(verr.mean()) < 0.02 and abs(verr.std() - 0.5) < 0.02
    # clutter uniform over the image, velocities N(0, 0.5^2)
    cl = det.centers()[~true]
    assert cl.min() >= 0 and cl[:, 0].max() < 400 and cl[:, 1].max() < 300
    assert abs(cl[:, 0].mean() - 200) < 15 and abs(cl[:, 1].mean() - 150) < 12
    assert abs(det.velocity()[~true].std() - 0.5) < 0.05


def test_truth_velocity_finite_differences():
    truth, vel = moving_truth(frames=30, objects=8)
    v = truth_velocity(truth)
    np.testing.assert_allclose(v, vel[truth.id], atol=1e-9)  # gaps divide by the frame step
    single = from_points([5], [1], [3.0], [4.0])
    np.testing.assert_array_equal(truth_velocity(single), [[0.0, 0.0]])
    two = from_points([2, 1], [1, 1], [3.0, 1.0], [0.0, 0.0])  # unsorted input, birth gets forward diff
    np.testing.assert_allclose(truth_velocity(two), [[2.0, 0.0], [2.0, 0.0]])


def test_same_seed_same_detections_and_velocity_does_not_move_positions():
    truth, _ = moving_truth(frames=20, objects=10)
    a = simulate_detections(truth, 0.9, 1.0, 3.0, (400, 300), 1.0, torch.Generator().manual_seed(7))
    b = simulate_detections(truth, 0.9, 1.0, 3.0, (400, 300), 1.0, torch.Generator().manual_seed(7))
    c = simulate_detections(truth, 0.9, 1.0, 3.0, (400, 300), None, torch.Generator().manual_seed(7))
    d = simulate_detections(truth, 0.9, 1.0, 3.0, (400, 300), 1.0, torch.Generator().manual_seed(8))
    for x, y in zip(a.detections, b.detections):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.detections.centers(), c.detections.centers())
    assert c.detections.vx is None
    assert a.detections.size != d.detections.size or not np.array_equal(a.detections.x, d.detections.x)


def test_empty_frames_and_huge_clutter():
    truth = from_points([1, 60], [1, 1], [5.0, 6.0], [5.0, 6.0])  # 58 frames without any object
    sim = simulate_detections(truth, 1.0, 0.0, 0.0, (10, 10), None, torch.Generator().manual_seed(0))
    assert sim.detections.size == 2
    truth = from_points([1, 3], [1, 1], [5.0, 6.0], [5.0, 6.0])
    sim = simulate_detections(truth, 1.0, 0.0, 30000.0, (1000, 1000), None, torch.Generator().manual_seed(0))
    per_frame = np.bincount(sim.detections.frame)       # clutter in the frames the truth holds, 1 and 3
    assert per_frame[[1, 3]].min() > 29000 and sim.detections.frames().tolist() == [1, 3]


def test_bad_arguments():
    truth, _ = moving_truth(frames=2, objects=2)
    with pytest.raises(TorchtrackError, match="pd"):
        simulate_detections(truth, 1.5, 1.0, 1.0, (10, 10))
    with pytest.raises(TorchtrackError, match="sigma"):
        simulate_detections(truth, 0.5, -1.0, 1.0, (10, 10))
    with pytest.raises(TorchtrackError, match="image_size"):
        simulate_detections(truth, 0.5, 1.0, 1.0, (0, 10))


def test_cli_round_trip(tmp_path):
    truth, _ = moving_truth(frames=30, objects=10)
    write_motdata(tmp_path / "gt.txt", truth)
    args = ["simulate-detections", "--gt", str(tmp_path / "gt.txt"), "--pd", "0.9", "--sigma", "1",
            "--clutter", "2", "--velocity-sigma", "1", "--seed", "4", "--out"]
    assert main(args + [str(tmp_path / "a.txt"), "--json", str(tmp_path / "a.json")]) == 0
    assert main(args + [str(tmp_path / "b.txt")]) == 0
    assert (tmp_path / "a.txt").read_text() == (tmp_path / "b.txt").read_text()
    det = read_mot(tmp_path / "a.txt")
    summary = json.loads((tmp_path / "a.json").read_text())
    assert det.size == summary["detections"] and det.velocity() is not None
    assert summary["image_size"] == list(default_image_size(truth))
    assert main(["simulate-detections", "--gt", str(tmp_path / "nope.txt"), "--out", str(tmp_path / "c.txt")]) == 2
