"""Adaptive birth (section 2.4): birth measurements (eq. 4), initial state (eq. 6), velocity map."""

from __future__ import annotations

import torch

from torchtrack.filters.gmphd.birth import AdaptiveBirth, VelocityMap
from torchtrack.filters.trackers.options import GMPHDBirthOptions, VelocityMapOptions

F64 = torch.float64


def test_birth_measurements_are_those_far_from_every_heavy_prediction():
    birth = AdaptiveBirth(GMPHDBirthOptions(distance_threshold=5.0, suppress_weight=0.1))
    pred_pos = torch.tensor([[0.0, 0.0], [100.0, 0.0], [50.0, 50.0]], dtype=F64)
    pred_logw = torch.tensor([0.0, 0.0, -5.0], dtype=F64)          # the third is too light to explain
    z = torch.tensor([[3.0, 4.0], [3.0, 4.1], [100.0, 6.0], [50.0, 50.0]], dtype=F64)
    assert birth.birth_measurements(pred_pos, pred_logw, z).tolist() == [False, True, True, True]
    assert birth.birth_measurements(pred_pos[:0], pred_logw[:0], z).all()


def test_velocity_map_answers_only_consistent_cells():
    vmap = VelocityMap(VelocityMapOptions(cell=10.0, min_count=2, max_spread=1.0), dtype=F64)
    # cell (0, 0): a one-way road; cell (0, 1): a two-way road; cell (0, 2): one sample only
    pos = torch.tensor([[1.0, 1.0], [5.0, 5.0], [12.0, 2.0], [15.0, 3.0], [25.0, 5.0]], dtype=F64)
    vel = torch.tensor([[3.0, 0.0], [3.2, 0.2], [5.0, 0.0], [-5.0, 0.0], [1.0, 1.0]], dtype=F64)
    vmap.update(pos, vel)
    v, ok = vmap.lookup(torch.tensor([[2.0, 8.0], [18.0, 1.0], [21.0, 1.0], [-3.0, 1.0]], dtype=F64))
    assert ok.tolist() == [True, False, False, False]
    torch.testing.assert_close(v[0], torch.tensor([3.1, 0.1], dtype=F64))


def test_initial_state_follows_equation_6():
    vmap = VelocityMap(VelocityMapOptions(cell=10.0, min_count=1), dtype=F64)
    vmap.update(torch.tensor([[5.0, 5.0]], dtype=F64), torch.tensor([[4.0, -2.0]], dtype=F64))
    birth = AdaptiveBirth(GMPHDBirthOptions(sigma_pos=2.0, sigma_vel_unknown=8.0, sigma_vel_detector=1.5,
                                            sigma_vel_map=2.5)).double()
    z = torch.tensor([[6.0, 6.0], [55.0, 55.0]], dtype=F64)
    v_det = torch.tensor([[1.0, 1.0], [-1.0, 2.0]], dtype=F64)
    mean, std, logw = birth(z, v_det, vmap)
    torch.testing.assert_close(mean, torch.tensor([[6.0, 6, 4, -2], [55, 55, -1, 2]], dtype=F64))   # map, then CNN
    torch.testing.assert_close(std[:, 2], torch.tensor([2.5, 1.5], dtype=F64), rtol=1e-6, atol=1e-6)
    mean, std, _ = birth(z, None, None)                                                   # neither: at rest
    torch.testing.assert_close(mean[:, 2:], torch.zeros(2, 2, dtype=F64))
    torch.testing.assert_close(std[:, 2], torch.full((2,), 8.0, dtype=F64), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(logw.exp(), torch.full((2,), 0.05, dtype=F64), rtol=1e-6, atol=1e-9)
