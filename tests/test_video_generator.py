"""The synthetic satellite video: determinism, truth where the vehicles are drawn, files, config errors."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.sim.video import VideoConfig, generate_sequence, load_video_config, read_camera, write_sequence

SMALL = VideoConfig(height=160, width=192, frames=4, margin=24, highways=1, local_roads=1, car_parks=1,
                    trees=40, speckles=30, buildings=3)


def _frames(cfg, seed):
    return list(generate_sequence(cfg, torch.Generator().manual_seed(seed)))


def test_deterministic_for_a_seed():
    a, b, c = _frames(SMALL, 5), _frames(SMALL, 5), _frames(SMALL, 6)
    for fa, fb in zip(a, b):
        assert np.array_equal(fa.image, fb.image)
        assert np.array_equal(fa.ids, fb.ids) and np.array_equal(fa.xy, fb.xy)
        assert np.array_equal(fa.homography, fb.homography)
    assert not np.array_equal(a[0].image, c[0].image)


def test_truth_is_where_the_vehicles_are_drawn():
    # no clutter, no noise, no blur: each isolated vehicle's contrast centroid must sit on its truth point
    cfg = SMALL.replace(trees=0, speckles=0, buildings=0, noise_std=0.0, psf_sigma=0.0, gain_drift=0.0,
                        frames=6, vehicle_length=(5.0, 9.0), height=256, width=256, highways=2,
                        local_roads=2, car_parks=0)
    frames = _frames(cfg, 2)
    errors = []
    for f in frames:
        img = f.image.astype(np.float64)
        bg = cv2.medianBlur(f.image, 21).astype(np.float64)
        contrast = np.abs(img - bg)
        for i, (x, y) in enumerate(f.xy):
            others = np.delete(f.xy, i, axis=0)
            if len(others) and np.min(np.linalg.norm(others - f.xy[i], axis=1)) < 16:
                continue
            r = 7
            x0, y0 = int(round(x)) - r, int(round(y)) - r
            if x0 < 0 or y0 < 0 or x0 + 2 * r + 1 > cfg.width or y0 + 2 * r + 1 > cfg.height:
                continue
            win = contrast[y0:y0 + 2 * r + 1, x0:x0 + 2 * r + 1]
            win = np.where(win > 0.3 * win.max(), win, 0.0)
            ys, xs = np.mgrid[0:2 * r + 1, 0:2 * r + 1]
            cx, cy = (win * xs).sum() / win.sum() + x0, (win * ys).sum() / win.sum() + y0
            errors.append(np.hypot(cx - x, cy - y))
    assert len(errors) >= 10
    assert np.median(errors) < 0.6
    # a swapped x/y convention or a wrong homography would put the truth off the drawn vehicles
    assert np.quantile(errors, 0.8) < 1.5


def test_velocity_is_displacement_between_frames():
    frames = _frames(SMALL, 1)
    for prev, cur in zip(frames, frames[1:]):
        common, ip, ic = np.intersect1d(prev.ids, cur.ids, return_indices=True)
        assert len(common) > 5
        np.testing.assert_allclose(cur.velocity[ic], cur.xy[ic] - prev.xy[ip], atol=1e-9)


def test_writer_files_match_the_generator(tmp_path):
    out = write_sequence(SMALL, torch.Generator().manual_seed(3), tmp_path / "seq")
    frames = _frames(SMALL, 3)
    pngs = sorted((out / "frames").glob("*.png"))
    assert [p.name for p in pngs] == [f"{k:06d}.png" for k in range(1, SMALL.frames + 1)]
    assert np.array_equal(cv2.imread(str(pngs[1]), cv2.IMREAD_UNCHANGED), frames[1].image)
    gt = np.loadtxt(out / "gt.txt", delimiter=",")
    half = SMALL.gt_box_size / 2
    for f in frames:
        rows = gt[gt[:, 0] == f.index + 1]
        order = np.argsort(rows[:, 1])
        np.testing.assert_array_equal(rows[order, 1], np.sort(f.ids))
        centres = rows[order, 2:4] + half
        np.testing.assert_allclose(centres, f.xy[np.argsort(f.ids)], atol=2e-3)
        assert np.all(rows[:, 4:6] == SMALL.gt_box_size) and np.all(rows[:, 7:] == -1)
    H = read_camera(out / "camera.json")
    np.testing.assert_allclose(H, np.stack([f.homography for f in frames]))
    assert "convention" in json.loads((out / "camera.json").read_text())


def test_config_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("video:\n  height: 256\n  wheels: 4\n")
    with pytest.raises(TorchtrackError, match="wheels"):
        load_video_config(bad)
    with pytest.raises(TorchtrackError, match="vehicle_length"):
        VideoConfig(vehicle_length=(9.0, 3.0))
    good = tmp_path / "good.yaml"
    good.write_text("video:\n  height: 256\n  vehicle_length: [4, 8]\n")
    assert load_video_config(good) == VideoConfig(height=256, vehicle_length=(4.0, 8.0))
    bad_cam = tmp_path / "camera.json"
    bad_cam.write_text("{}")
    with pytest.raises(TorchtrackError, match="camera.json"):
        read_camera(bad_cam)


def test_yaml_config_equals_the_defaults_and_numbers_are_numbers(tmp_path):
    shipped = Path(__file__).resolve().parents[1] / "configs" / "video.yaml"
    assert load_video_config(shipped) == VideoConfig()
    path = tmp_path / "v.yaml"
    path.write_text("video:\n  jitter_perspective: 2e-06\n  speed_median: 12\n")   # YAML 1.1: a string
    cfg = load_video_config(path)
    assert cfg.jitter_perspective == 2e-06 and isinstance(cfg.speed_median, float)
    path.write_text("video:\n  speed_median: fast\n")
    with pytest.raises(TorchtrackError, match="speed_median"):
        load_video_config(path)


def test_a_larger_view_keeps_the_density_of_the_scene():
    """Up to 512² the configured counts are drawn as they are; a 1024² view holds four times the point objects
    (trees, speckles, buildings, car parks: area) and twice the roads (side) — the same density per area."""
    from torchtrack.sim.video_scene import build_scene

    small, large = VideoConfig(height=256, width=256), VideoConfig(height=1024, width=1024)
    scene_small = build_scene(small, np.random.default_rng(0))
    scene_large = build_scene(large, np.random.default_rng(0))
    assert len(scene_small.buildings) == small.buildings
    assert len(scene_large.buildings) == 4 * large.buildings
    # a highway has 2-3 lanes each way, a local road one: 4 highways and 6 local roads make at least 28 lanes,
    # more than 2 highways and 3 local roads can (at most 18)
    assert len(scene_large.lanes) >= 2 * (2 * 2 * large.highways) + 2 * (2 * large.local_roads)
