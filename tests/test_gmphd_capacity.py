"""The GM-PHD's component cap follows the scene: ``max(capacity, 2 (measurements + live labels))``."""

import pytest
import torch

from torchtrack.bench import scale
from torchtrack.errors import TorchtrackError
from torchtrack.filters.gmphd.filter import GMPHD, SCENE_COMPONENTS
from torchtrack.filters.trackers.options import GMPHDFilterOptions
from torchtrack.filters.trackers.protocol import make_tracker


def test_capacity_is_the_floor_of_a_cap_sized_from_the_scene():
    phd = GMPHD(options=GMPHDFilterOptions(capacity=100))
    assert phd.capacity_for(10, 20) == 100
    assert phd.capacity_for(300, 200) == SCENE_COMPONENTS * 500 == 1000


def test_a_scene_past_the_configured_limit_is_an_error_naming_it():
    tracker = make_tracker("gmphd", {"filter": {"capacity": 64, "capacity_limit": 500}})
    scene = scale.simulate(300, 3, seed=1)                  # 300 vehicles: more than 250 measurements a frame
    with pytest.raises(TorchtrackError, match="capacity_limit 500"):
        for frame, z, v in scene.detections:
            tracker.step(frame, z, v)
    roomy = GMPHD(options=GMPHDFilterOptions(capacity=64, capacity_limit=10_000))
    assert roomy.capacity_for(300, 200) == 1000              # a limit above the scene changes nothing


@pytest.mark.parametrize("name", ["gmphd", "labelled-gmphd"])
def test_a_small_configured_capacity_drops_no_live_component(name):
    """300 vehicles hold far more than 64 components; with ``capacity: 64`` as the floor the tracks are those of
    a capacity no step can reach, and no cap is hit."""
    scene = scale.simulate(300, 10, seed=1)
    cpu = torch.device("cpu")
    small = scale.run_one(name, scene, cpu, 1e9, {"filter": {"capacity": 64}})
    roomy = scale.run_one(name, scene, cpu, 1e9, {"filter": {"capacity": 100_000}})
    assert small.cap_hits == 0 and roomy.cap_hits == 0
    assert small.mota == roomy.mota
    assert small.mota > 0.6

    tracker = make_tracker(name, {"filter": {"capacity": 64}})
    for frame, z, v in scene.detections:
        tracker.step(frame, z, v)
    assert tracker.state.size > 4 * 64                   # the old constant cap would have dropped most of them


def test_the_merge_screen_finds_the_same_pairs_as_testing_every_pair():
    """The grid screen of the merge returns exactly the pairs within reach, checked pair by pair (float64)."""
    from torchtrack.filters.gmphd.filter import _within_reach

    g = torch.Generator().manual_seed(4)
    J, U = 600, 9.0
    mean = torch.cat([torch.rand(J, 2, generator=g, dtype=torch.float64) * 200,
                      torch.randn(J, 2, generator=g, dtype=torch.float64)], 1)
    mean[:50, :2] = mean[50:100, :2] + 0.5                     # some near-duplicates
    A = torch.randn(J, 4, 4, generator=g, dtype=torch.float64)
    scale_ = torch.rand(J, 1, 1, generator=g, dtype=torch.float64) * 20
    cov = A @ A.transpose(1, 2) * scale_ + 0.1 * torch.eye(4, dtype=torch.float64)
    ii, jj = _within_reach(mean, cov, U)
    found = set(zip(ii.tolist(), jj.tolist()))
    truth = set()
    for i in range(J):
        diff = mean[:i] - mean[i]                                        # m_j − m_i for every heavier j < i
        d2 = (diff @ torch.linalg.inv(cov[i]) * diff).sum(1)            # independent of the Cholesky path
        truth |= {(i, j) for j in (d2 <= U).nonzero().flatten().tolist()}
    assert len(truth) > 50 and found == truth
