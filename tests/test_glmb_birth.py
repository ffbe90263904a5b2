"""The GLMB's adaptive birth: the existence of each birth row (B1), the birth rate that follows the area of the
frame's detections (B2), births that still happen in a scene of 1000 vehicles, and the two-point birth (B3)."""

import math

import numpy as np
import torch

from torchtrack.bench.scale import simulate
from torchtrack.filters.glmb.birth import adaptive_births, scene_birth_rate, two_point_births
from torchtrack.filters.trackers.protocol import make_tracker


def test_birth_rate_is_the_larger_of_the_floor_and_the_density_times_the_extent():
    z = torch.tensor([[100.0, 50.0], [1100.0, 250.0], [600.0, 2050.0]], dtype=torch.float64)   # 1000 × 2000 px
    assert scene_birth_rate(z, 0.3, 1.5) == 1.5 * 2.0
    assert scene_birth_rate(z, 0.3, 0.1) == 0.3
    assert scene_birth_rate(z[:1], 0.3, 100.0) == 0.3        # one detection spans no area
    assert scene_birth_rate(z[:0], 0.3, 100.0) == 0.3


def test_birth_existence_is_b1_with_the_given_rate():
    z = torch.tensor([[0.0, 0.0], [5.0, 5.0], [9.0, 1.0], [3.0, 7.0]], dtype=torch.float64)
    used = torch.tensor([0.0, 0.5, 1.0, 0.9999], dtype=torch.float64)       # Σ (1 − r_U) = 1.5001

    def births(rate, used=used):
        return adaptive_births(z, None, used, frame=4, next_index=10, birth_rate=rate, r_max=0.5, r_min=1e-3,
                               sigma_pos=2.0, sigma_vel=8.0, sigma_vel_detector=1.5)

    low = births(0.6)            # rows 3 (0.6 · 1e-4 / 1.5001) and 2 (fully explained) are below r_min
    np.testing.assert_allclose(low.log_r.exp().numpy(), [0.6 / 1.5001, 0.3 / 1.5001], rtol=1e-12)
    np.testing.assert_array_equal(low.mean.numpy(), [[0.0, 0.0, 0.0, 0.0], [5.0, 5.0, 0.0, 0.0]])
    assert low.label.tolist() == [[4, 10], [4, 11]]
    np.testing.assert_allclose(births(3.0).log_r.exp().numpy(), [0.5, 0.5], rtol=1e-12)       # capped at r_max
    few = births(0.6, torch.tensor([0.9, 0.8, 1.0, 1.0], dtype=torch.float64))    # Σ (1 − r_U) < 1: not divided
    np.testing.assert_allclose(few.log_r.exp().numpy(), [0.06, 0.12], rtol=1e-12)


def test_two_point_births_are_b3_written_out():
    """Each measurement pairs with the nearest unexplained measurements of the previous frame within the maximum
    speed; the pairs share its (B1) existence by how unexplained the partner was, never more than all of it."""
    t = lambda a: torch.tensor(a, dtype=torch.float64)   # noqa: E731
    z = t([[100.0, 100.0], [200.0, 200.0], [400.0, 50.0], [500.0, 400.0]])
    used = t([0.0, 0.4, 0.9, 0.0])                       # Σ (1 − r_U) = 2.7
    z_prev = t([[90.0, 95.0], [104.0, 100.0], [100.0, 80.0], [130.0, 100.0], [185.0, 200.0], [400.0, 50.0]])
    # partners of z_0: [104, 100] (4 px, half explained), [90, 95] (11.2 px); [100, 80] (20 px) was explained,
    # [130, 100] (30 px) is beyond the 25 px/frame; z_1: [185, 200]; z_2: [400, 50] (at rest, 0.2 explained);
    # z_3: none
    used_prev = t([0.0, 0.5, 1.0, 0.0, 0.0, 0.2])

    def births(pairs):
        return two_point_births(z, used, z_prev, used_prev, frame=4, next_index=10, birth_rate=0.6, r_max=0.5,
                                r_min=1e-3, max_speed=25.0, pairs=pairs, sigma_pos=2.0, sigma_vel=1.5)

    r = 0.6 * np.array([1.0, 0.6, 0.1]) / 2.7
    b = births(3)
    np.testing.assert_allclose(b.log_r.exp().numpy(), [r[0] * 0.5 / 1.5, r[0] * 1.0 / 1.5, r[1], r[2] * 0.8],
                               rtol=1e-12)
    np.testing.assert_array_equal(b.mean.numpy(), [[100, 100, -4, 0], [100, 100, 10, 5], [200, 200, 15, 0],
                                                   [400, 50, 0, 0]])
    np.testing.assert_array_equal(b.cov.numpy(), np.broadcast_to(np.diag([4.0, 4.0, 2.25, 2.25]), (4, 4, 4)))
    assert b.label.tolist() == [[4, 10], [4, 11], [4, 12], [4, 13]]
    one = births(1)                                       # only the nearest partner: (1 − r_U) of it
    np.testing.assert_allclose(one.log_r.exp().numpy(), r * [0.5, 1.0, 0.8], rtol=1e-12)
    np.testing.assert_array_equal(one.mean[:, 2:].numpy(), [[-4, 0], [15, 0], [0, 0]])
    first = two_point_births(z, used, z_prev[:0], used_prev[:0], 1, 0, 0.6, 0.5, 1e-3, 25.0, 3, 2.0, 1.5)
    assert first.mean.shape == (0, 4) and first.label.shape == (0, 2)        # no previous frame: no birth


def test_tracks_start_in_a_scene_of_1000_vehicles():
    """Bench scale's constant-density scene, N = 1000 (~1150 detections a frame): with a fixed λ_B = 0.3 every
    birth row is below birth_min and nothing is ever reported; λ_B from the scene's area starts the tracks."""
    scene = simulate(1000, 6, seed=1)
    reported = {}
    for density in (0.0, 1.0):
        tracker = make_tracker("glmb", {"birth_density": density})
        for frame, z, v in scene.detections:
            ids, _ = tracker.step(frame, z, v)
        reported[density] = ids.numel()
    assert reported[0.0] == 0
    assert reported[1.0] > 500
    assert math.isclose(scene.side**2 * 1e-6, 3.6)


def test_two_point_partners_from_the_grid_equal_every_pair_compared(monkeypatch):
    """The two-point birth's nearest free partners within the maximum speed: the grid path (wide-area frames)
    gives the distances and partners of comparing every pair (float64, random frames, ties impossible)."""
    from torchtrack.filters.glmb import birth as glmb_birth

    g = torch.Generator().manual_seed(7)
    z = torch.rand(400, 2, generator=g, dtype=torch.float64) * 300
    z_prev = torch.rand(350, 2, generator=g, dtype=torch.float64) * 300
    free = torch.rand(350, generator=g) > 0.3
    dense = glmb_birth._nearest_partners(z, z_prev, free, 25.0, 3)
    monkeypatch.setattr(glmb_birth, "DENSE_PAIRS", 0)
    grid = glmb_birth._nearest_partners(z, z_prev, free, 25.0, 3)
    assert torch.isfinite(dense[0]).sum() > 500 and (~torch.isfinite(dense[0])).any()
    torch.testing.assert_close(grid[0], dense[0], rtol=0, atol=1e-12)
    found = torch.isfinite(dense[0])
    assert torch.equal(grid[1][found], dense[1][found])
