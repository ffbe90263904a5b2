"""The ``pmb`` entry of the streaming tracker registry."""

from __future__ import annotations

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import make_tracker, tracker_names


def test_pmb_tracker_follows_two_targets_with_stable_ids():
    assert "pmb" in tracker_names()
    tracker = make_tracker("pmb", {"region": [0, 0, 200, 200], "clutter_rate": 2.0, "sigma": 1.0})
    g = torch.Generator().manual_seed(0)
    seen = []
    for frame in range(1, 26):
        truth = torch.tensor([[20.0 + 2 * frame, 50.0], [150.0, 160.0 - frame]], dtype=torch.float64)
        z = truth + torch.randn(2, 2, generator=g, dtype=torch.float64)
        clutter = torch.rand(2, 2, generator=g, dtype=torch.float64) * 200
        ids, pos = tracker.step(frame, torch.cat([z, clutter]))
        if frame > 5:
            assert 2 <= ids.numel() <= 3                 # both targets, at most a short-lived clutter track
            d = torch.cdist(truth, pos)
            assert float(d.min(1).values.max()) < 3.0
            seen.append(tuple(ids[d.argmin(1)].tolist()))
    assert len(set(seen)) == 1                       # the same id on each target throughout
    with pytest.raises(TorchtrackError, match="frames must increase"):
        tracker.step(3, torch.zeros(0, 2))
    with pytest.raises(TorchtrackError, match=r"unknown key\(s\) \['pmb.nonsense'\]"):
        make_tracker("pmb", {"nonsense": 1})
