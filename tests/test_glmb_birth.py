"""The GLMB's adaptive birth: the existence of each birth row (B1), the birth rate that follows the area of the
frame's detections (B2), and births that still happen in a scene of 1000 vehicles."""

import math

import numpy as np
import torch

from torchtrack.bench.scale import simulate
from torchtrack.filters.glmb_birth import adaptive_births, scene_birth_rate
from torchtrack.filters.multitarget import make_tracker


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
