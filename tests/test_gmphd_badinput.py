"""Bad input for the GM-PHD trackers: empty frames, huge frames, wrong shapes, non-increasing frames."""

from __future__ import annotations

import logging

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import make_tracker


def _target(k: int) -> torch.Tensor:
    return torch.tensor([[50.0 + 3.0 * k, 80.0], [200.0, 40.0 + 2.0 * k]])


@pytest.mark.parametrize("name", ["gmphd", "labelled-gmphd"])
def test_many_empty_frames_then_targets(name):
    tracker = make_tracker(name, None)
    for k in range(1, 61):
        ids, pos = tracker.step(k, torch.zeros(0, 2), None)
        assert ids.shape == (0,) and pos.shape == (0, 2)
    assert tracker.state.size == 0
    for k in range(61, 71):
        ids, pos = tracker.step(k, _target(k), torch.tensor([[3.0, 0.0], [0.0, 2.0]]))
    assert len(set(ids.tolist())) == 2                       # both targets confirmed after the gap
    for k in range(71, 120):                                # targets vanish: tracks die, mixture empties
        ids, _ = tracker.step(k, torch.zeros(0, 2), torch.zeros(0, 2))
    assert ids.numel() == 0 and tracker.state.size == 0


@pytest.mark.parametrize("velocity_sigma", [None, 1.5])
def test_thousands_of_detections_bounded_by_the_scene(velocity_sigma):
    """8000 detections a frame: the mixture stays within the cap sized from the measurements and live labels
    (far above the configured floor of 512), and the tracker keeps working afterwards."""
    from torchtrack.filters.gmphd.filter import GMPHD
    from torchtrack.filters.trackers.options import GMPHDFilterOptions

    tracker = make_tracker("gmphd", {"filter": {"capacity": 512, "chunk": 2048, "velocity_sigma": velocity_sigma}})
    phd = GMPHD(options=GMPHDFilterOptions(capacity=512))
    g = torch.Generator().manual_seed(0)
    before = 0
    for k in range(1, 3):
        z = torch.rand(8000, 2, generator=g) * 600
        tracker.step(k, z, torch.zeros(8000, 2))
        assert 512 < tracker.state.size <= phd.capacity_for(8000, before)   # live labels <= components before
        before = tracker.state.size
    ids, _ = tracker.step(3, _target(3), None)
    assert ids.numel() <= before


def test_bad_input_is_a_clear_error():
    tracker = make_tracker("gmphd", None)
    tracker.step(5, _target(5), None)
    with pytest.raises(TorchtrackError, match="frames must increase"):
        tracker.step(5, _target(5), None)
    with pytest.raises(TorchtrackError, match="unknown tracker"):
        make_tracker("nope", None)
    with pytest.raises(TorchtrackError, match=r"unknown key\(s\) \['gmphd.fliter'\]"):
        make_tracker("gmphd", {"fliter": {}})
    with pytest.raises(TorchtrackError, match=r"unknown key\(s\) \['gmphd.filter.nonsense'\]"):
        make_tracker("gmphd", {"filter": {"p_detection": 0.9, "nonsense": 1}})
    with pytest.raises(TorchtrackError, match="p_detection"):
        make_tracker("gmphd", {"filter": {"p_detection": 1.5}})
    for bad in (0, 2.5, "3"):
        with pytest.raises(TorchtrackError, match="confirm_new"):
            make_tracker("gmphd", {"confirm_new": bad})
    with pytest.raises(TorchtrackError, match="confirm_misses"):
        make_tracker("gmphd", {"confirm_misses": -1})


@pytest.mark.parametrize("name", ["gmphd", "labelled-gmphd"])
def test_long_sequence_memory_bounded_and_every_cap_hit_reported(caplog, name):
    """Hundreds of frames of dense clutter without merging or pruning (every gated pair stays a component): the
    mixture never exceeds the scene's cap ``max(capacity, 2 (M + live labels))``, each hit is logged and
    counted; with merging and pruning, the cap is never reached."""
    from torchtrack.filters.gmphd.filter import GMPHD
    from torchtrack.filters.trackers.options import GMPHDFilterOptions

    g = torch.Generator().manual_seed(1)
    frames = [torch.rand(60, 2, generator=g) * 400 for _ in range(300)]
    tight = make_tracker(name, {"filter": {"capacity": 40, "merge_threshold": 0.0, "prune_threshold": 1e-30}})
    phd = GMPHD(options=GMPHDFilterOptions(capacity=40))
    before = 0
    with caplog.at_level(logging.WARNING, logger="torchtrack.filters.gmphd.filter"):
        for k, z in enumerate(frames, start=1):
            tight.step(k, z, torch.zeros_like(z))
            assert tight.state.size <= phd.capacity_for(60, before)    # live labels <= components before
            before = tight.state.size
    hits = sum("cap hit" in r.getMessage() for r in caplog.records)
    assert tight.cap_hits == hits > 100
    merged = make_tracker(name, {"filter": {"capacity": 40}})
    for k, z in enumerate(frames[:50], start=1):
        merged.step(k, z, torch.zeros_like(z))
    assert merged.cap_hits == 0 and merged.state.size > 40


def test_non_positive_definite_innovation_covariance_is_a_clear_error():
    from torchtrack.filters.gmphd.filter import GMPHD, MixtureState

    phd = GMPHD()
    state = MixtureState(torch.zeros(2), torch.zeros(2, 4), -10.0 * torch.eye(4).expand(2, 4, 4),
                         torch.arange(2), torch.ones(2, dtype=torch.bool))
    with pytest.raises(TorchtrackError, match=r"GMPHD update: innovation covariance S is not positive definite \(2 of"):
        phd.update(state, torch.zeros(1, 2), phd.matrices(1.0))
