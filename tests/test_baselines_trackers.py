"""SORT, greedy (CenterTrack) and the tracker factory."""

from __future__ import annotations

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import make_tracker, run_tracker, tracker_names


def crossing_scene(T=30, speed=6.0, with_velocity=True, noise=0.3, seed=0):
    """Three targets: two on parallel lanes 40 px apart, one crossing diagonally; no clutter, p_D = 1."""
    g = torch.Generator().manual_seed(seed)
    p0 = torch.tensor([[0.0, 100.0], [0.0, 140.0], [0.0, 0.0]])
    v = torch.tensor([[speed, 0.0], [speed, 0.0], [speed * 0.7, speed * 0.7]])
    frames = []
    for k in range(1, T + 1):
        z = p0 + v * k + noise * torch.randn(3, 2, generator=g)
        frames.append((k, z, v.clone() if with_velocity else None))
    return frames


def ids_per_target(results, frames):
    out = [set() for _ in range(3)]
    for (_, ids, pos), (_, z, _) in zip(results, frames):
        if ids.numel() == 0:
            continue
        d = torch.cdist(z.double(), pos.double())
        for t in range(3):
            j = int(d[t].argmin())
            if float(d[t, j]) < 5:
                out[t].add(int(ids[j]))
    return out


@pytest.mark.parametrize("name", ["gmphd", "labelled-gmphd", "sort", "greedy"])
def test_every_tracker_keeps_one_id_per_target_on_a_clean_scene(name):
    frames = crossing_scene()
    tracker = make_tracker(name, {"max_distance": 10.0} if name == "greedy" else None)
    results = run_tracker(tracker, frames)
    per_target = ids_per_target(results, frames)
    assert [len(s) for s in per_target] == [1, 1, 1], per_target
    assert len(set.union(*per_target)) == 3
    ids, pos = results[-1][1], results[-1][2]
    assert ids.numel() == 3 and pos.shape == (3, 2)


def test_greedy_needs_the_detector_velocity_for_fast_targets():
    fast = crossing_scene(speed=15.0)
    with_v = ids_per_target(run_tracker(make_tracker("greedy", None), fast), fast)
    assert [len(s) for s in with_v] == [1, 1, 1]
    no_v = [(k, z, None) for k, z, _ in fast]
    without = ids_per_target(run_tracker(make_tracker("greedy", None), no_v), no_v)
    assert all(len(s) > 10 for s in without)           # every frame a new id: 15 px > 10 px gate


def test_sort_rules_min_hits_and_max_age():
    tracker = make_tracker("sort", {"min_hits": 3, "max_age": 1})
    z = torch.tensor([[10.0, 10.0]])
    outs = [tracker.step(k, z + torch.tensor([[2.0 * k, 0.0]]), None)[0].tolist() for k in range(1, 8)]
    assert outs[0] == [1]                                 # reported during the first min_hits frames
    assert all(o == [1] for o in outs)
    tracker.step(8, torch.zeros(0, 2), None)             # one miss: kept (max_age 1), not reported
    assert tracker.step(9, torch.zeros(0, 2), None)[0].numel() == 0
    ids, _ = tracker.step(10, torch.tensor([[30.0, 10.0]]), None)
    assert ids.numel() == 0                               # track deleted: a new one starts, not yet confirmed
    assert int(tracker.ids.max()) == 2


def test_factory_names_and_errors():
    assert tracker_names()[:4] == ["gmphd", "labelled-gmphd", "sort", "greedy"]
    with pytest.raises(TorchtrackError, match=r"unknown key\(s\) \['sort.max_dist'\]"):
        make_tracker("sort", {"max_dist": 3})
    with pytest.raises(TorchtrackError, match=r"unknown key\(s\) \['greedy.foo'\]"):
        make_tracker("greedy", {"foo": 1})
    tracker = make_tracker("sort", None)
    tracker.step(3, torch.zeros(0, 2), None)
    with pytest.raises(TorchtrackError, match="frames must increase"):
        tracker.step(2, torch.zeros(0, 2), None)
