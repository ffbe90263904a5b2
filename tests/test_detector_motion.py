"""Motion pieces of the detector: block-matching velocity refinement and the matching cross-entropy."""

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter, shift

from torchtrack.detector.losses import matching_loss
from torchtrack.detector.network import CenterTrackNet
from torchtrack.detector.refine import continuity_refine, refine_velocity


def _texture(seed: int, size: int = 96) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return gaussian_filter(rng.normal(0, 1, (size, size)), 1.5)


@pytest.mark.parametrize("true_v", [(3.0, -5.0), (-7.0, 2.0), (2.4, -1.7)])
def test_refine_recovers_a_known_shift(true_v):
    prev = _texture(0)
    cur = shift(prev, (true_v[1], true_v[0]), order=3, mode="nearest")     # cur(p) = prev(p - v)
    xy = torch.tensor([[40.0, 50.0], [30.3, 35.8], [60.0, 44.0]], dtype=torch.float64)
    coarse = torch.tensor(true_v, dtype=torch.float64) + torch.tensor([[2.0, -1.0], [-1.0, 2.0], [0.0, 3.0]])
    v = refine_velocity(torch.from_numpy(cur), torch.from_numpy(prev), xy, coarse, patch=4, radius=4, pull=0.0)
    # the integer match is exact; the parabola through the neighbouring costs adds < 0.25 px
    np.testing.assert_allclose(v.numpy(), np.tile(true_v, (3, 1)), atol=0.25)


def test_refine_pull_prefers_the_coarse_estimate_among_equal_matches():
    prev = np.zeros((64, 64))
    prev[30:33, 20:23] = 1.0
    prev[30:33, 40:43] = 1.0        # two identical blobs 20 px apart: displacements -+10 match equally well
    cur = np.zeros((64, 64))
    cur[30:33, 30:33] = 1.0
    xy = torch.tensor([[31.0, 31.0]])
    for coarse, expect in [((9.0, 0.0), (10.0, 0.0)), ((-9.0, 0.0), (-10.0, 0.0))]:
        v = refine_velocity(torch.from_numpy(cur), torch.from_numpy(prev), xy.double(),
                            torch.tensor([coarse], dtype=torch.float64), patch=3, radius=12, pull=1e-3)
        np.testing.assert_allclose(v[0].numpy(), expect, atol=0.05)


def test_matching_loss_matches_brute_force():
    torch.manual_seed(0)
    r, cell, f = 2, 8.0, 4
    logits = torch.randn(2, (2 * r + 1) ** 2, 3, 3, dtype=torch.float64)
    velocity = torch.zeros(2, 2, 12, 12, dtype=torch.float64)
    mask = torch.zeros(2, 12, 12, dtype=torch.bool)
    cells = [(0, 1, 5, (4.0, -10.0)), (0, 11, 2, (-3.0, 0.5)), (1, 7, 7, (0.0, 0.0)), (1, 3, 3, (40.0, 0.0))]
    for b, i, j, v in cells:
        velocity[b, :, i, j] = torch.tensor(v, dtype=torch.float64)
        mask[b, i, j] = True
    expect = torch.zeros(2, dtype=torch.float64)
    counts = torch.zeros(2)
    for b, i, j, v in cells:
        bx, by = -v[0] / cell + r, -v[1] / cell + r
        if not (0 <= bx <= 2 * r and 0 <= by <= 2 * r):
            continue                                      # beyond the grid: not supervised
        logp = torch.log_softmax(logits[b, :, i // f, j // f], 0)
        total = 0.0
        for iy in range(2 * r + 1):
            for ix in range(2 * r + 1):
                w = max(0.0, 1 - abs(ix - bx)) * max(0.0, 1 - abs(iy - by))
                total -= w * logp[iy * (2 * r + 1) + ix]
        expect[b] += total
        counts[b] += 1
    got = matching_loss(logits, velocity, mask, cell)
    torch.testing.assert_close(got, expect / counts.clamp(min=1).double())


def test_matching_bins_are_the_network_displacements():
    net = CenterTrackNet(radius=2)
    # bin (ix, iy) = (3, 0): the object was 8 px right and 16 px up, so v = (-8, 16)
    np.testing.assert_allclose(net.displacement[:, 0 * 5 + 3].numpy(), [8.0, -16.0])
    logits = torch.full((1, 25, 1, 1), -30.0)
    logits[0, 3] = 30.0
    v = torch.tensor([-8.0, 16.0]).view(1, 2, 1, 1).repeat(1, 1, 8, 8)
    assert matching_loss(logits, v, torch.ones(1, 8, 8, dtype=torch.bool), 8.0).item() < 1e-6


def test_continuity_resolves_a_platoon():
    def frame(xs):
        img = np.zeros((64, 80))
        for x in xs:
            img[29:32, x - 1:x + 2] = 1.0
        return torch.from_numpy(gaussian_filter(img, 0.7))

    prev, cur = frame([20, 30]), frame([30, 40])          # both vehicles moved +10 px: the follower now
    xy = torch.tensor([[30.0, 30.0], [40.0, 30.0]], dtype=torch.float64)   # stands where the leader was
    coarse = torch.tensor([[0.0, 0.0], [10.0, 0.0]], dtype=torch.float64)
    v = refine_velocity(cur, prev, xy, coarse, patch=3, radius=2, pull=1e-3)
    np.testing.assert_allclose(v[0].numpy(), [0.0, 0.0], atol=0.05)   # zero displacement matches as well
    pts = torch.tensor([[20.0, 30.0], [30.0, 30.0]], dtype=torch.float64)
    pv = torch.tensor([[10.0, 0.0], [10.0, 0.0]], dtype=torch.float64)
    v2 = continuity_refine(cur, prev, xy, v, pts, pv, patch=3, reach=4.0)
    np.testing.assert_allclose(v2.numpy(), [[10.0, 0.0], [10.0, 0.0]], atol=0.05)
    far = continuity_refine(cur, prev, xy, v, pts + 20.0, pv, patch=3, reach=4.0)   # nothing predicted near
    torch.testing.assert_close(far, v)


def test_camera_velocity_is_the_motion_of_parked_vehicles():
    from torchtrack.detector.evaluate import camera_velocity
    from torchtrack.sim.video import generate_sequence
    from torchtrack.sim.video_config import from_dict

    video = from_dict({"height": 128, "width": 128, "margin": 16, "car_parks": 2, "frames": 3})
    frames = list(generate_sequence(video, torch.Generator().manual_seed(3)))
    for a, b in zip(frames[:-1], frames[1:]):
        parked = ~b.moving & ~np.isnan(b.velocity).any(1)
        assert parked.sum() > 3
        np.testing.assert_allclose(camera_velocity(b.xy[parked], a.homography @ np.linalg.inv(b.homography)),
                                   b.velocity[parked], atol=1e-6)
