"""PMB's Bernoulli slots follow the scene: every Bernoulli above the pruning threshold is kept (``capacity`` is
the floor), a configured ``capacity_limit`` is a clear error, and births follow the region's area."""

from __future__ import annotations

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb.tracker import birth_weight
from torchtrack.filters.trackers.options import tracker_config
from torchtrack.filters.trackers.protocol import make_tracker

SPACING = 40.0


def _grid_scene(side: int, frames: int, seed: int = 0):
    """``side²`` targets on a grid ``SPACING`` px apart moving right at 1 px/frame, each detected every frame
    with 1 px noise, no clutter: per frame ``(truth (K, 2), detections (K, 2))``."""
    g = torch.Generator().manual_seed(seed)
    axis = SPACING * (torch.arange(side, dtype=torch.float64) + 1)
    start = torch.cartesian_prod(axis, axis)
    for frame in range(frames):
        truth = start + torch.tensor([float(frame), 0.0], dtype=torch.float64)
        yield truth, truth + torch.randn(truth.shape, generator=g, dtype=torch.float64)


def test_more_targets_than_the_default_capacity_are_all_kept():
    """625 targets against the default ``capacity`` of 512: the old constant kept at most 512 of them."""
    side, frames = 25, 6
    extent = SPACING * (side + 1)
    tracker = make_tracker("pmb", {"region": [0.0, 0.0, extent + frames, extent], "clutter_rate": 0.1,
                                   "sigma": 1.0})
    assert tracker.filter.capacity == 512
    scene = list(_grid_scene(side, frames))
    for frame, (_, z) in enumerate(scene, 1):
        ids, pos = tracker.step(frame, z)
    truth = scene[-1][0]
    assert ids.numel() == side**2 == 625 and torch.unique(ids).numel() == 625
    assert float(torch.cdist(truth, pos).min(1).values.max()) < 4.0      # one estimate on every target
    assert tracker.state.existence.shape[-1] >= 625                    # the slots grew with the scene


def test_a_configured_capacity_limit_is_an_error_naming_it():
    tracker = make_tracker("pmb", {"region": [0.0, 0.0, 300.0, 300.0], "capacity": 16, "capacity_limit": 30})
    _, z = next(_grid_scene(6, 1))
    tracker.step(1, z[:30])                                             # 30 new Bernoullis: at the limit
    with pytest.raises(TorchtrackError, match="36 Bernoullis .* capacity_limit 30"):
        make_tracker("pmb", {"region": [0.0, 0.0, 300.0, 300.0], "capacity": 16, "capacity_limit": 30}).step(1, z)
    with pytest.raises(TorchtrackError, match="capacity_limit must be >= 1"):
        tracker_config("pmb", {"capacity_limit": 0})


def test_a_limit_above_the_scene_changes_nothing():
    runs = []
    for options in ({}, {"capacity": 8, "capacity_limit": 10_000}):
        tracker = make_tracker("pmb", {"region": [0.0, 0.0, 300.0, 300.0], "sigma": 1.0, **options})
        runs.append([tracker.step(frame, z) for frame, (_, z) in enumerate(_grid_scene(6, 5), 1)])
    for (ids_a, pos_a), (ids_b, pos_b) in zip(*runs):
        assert torch.equal(ids_a, ids_b)
        torch.testing.assert_close(pos_a, pos_b, rtol=0, atol=1e-9)


def test_births_follow_the_region_area():
    """``max(birth_weight, birth_density · area)``: the default 1024² region keeps ``birth_weight``; a region
    of 36 megapixels (10,000 vehicles at one per 60 × 60 px) gets 36 times ``birth_density``."""
    assert birth_weight(tracker_config("pmb")) == 0.1
    big = tracker_config("pmb", {"region": [0.0, 0.0, 6000.0, 6000.0]})
    assert birth_weight(big) == pytest.approx(36.0 * big.birth_density)
    assert birth_weight(tracker_config("pmb", {"region": [0.0, 0.0, 6000.0, 6000.0], "birth_density": 0.0})) == 0.1
