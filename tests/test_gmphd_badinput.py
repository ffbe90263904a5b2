"""Bad input for the GM-PHD trackers: empty frames, huge frames, wrong shapes, non-increasing frames."""

from __future__ import annotations

import logging

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.multitarget import make_tracker


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
def test_tens_of_thousands_of_detections_bounded_and_reported(caplog, velocity_sigma):
    tracker = make_tracker("gmphd", {"filter": {"capacity": 512, "chunk": 2048, "velocity_sigma": velocity_sigma}})
    g = torch.Generator().manual_seed(0)
    with caplog.at_level(logging.WARNING, logger="torchtrack.filters.gmphd"):
        for k in range(1, 3):
            z = torch.rand(20000, 2, generator=g) * 600
            tracker.step(k, z, torch.zeros(20000, 2))
            assert tracker.state.size <= 512
    assert tracker.cap_hits >= 1
    assert any("cap hit" in r.getMessage() for r in caplog.records)
    ids, _ = tracker.step(3, _target(3), None)             # and it keeps working afterwards
    assert ids.numel() <= 512


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
    """Hundreds of frames of dense clutter: the mixture never exceeds the cap, each hit is logged and counted;
    with room to spare the cap is never reported."""
    g = torch.Generator().manual_seed(1)
    frames = [torch.rand(60, 2, generator=g) * 400 for _ in range(300)]
    tight = make_tracker(name, {"filter": {"capacity": 40}})
    with caplog.at_level(logging.WARNING, logger="torchtrack.filters.gmphd"):
        for k, z in enumerate(frames, start=1):
            tight.step(k, z, torch.zeros_like(z))
            assert tight.state.size <= 40
    hits = sum("cap hit" in r.getMessage() for r in caplog.records)
    assert tight.cap_hits == hits > 100          # every frame's births overflow 40 slots: counted and logged
    roomy = make_tracker(name, {"filter": {"capacity": 4096}})
    for k, z in enumerate(frames[:50], start=1):
        roomy.step(k, z, torch.zeros_like(z))
    assert roomy.cap_hits == 0 and roomy.state.size < 4096


def test_non_positive_definite_innovation_covariance_is_a_clear_error():
    from torchtrack.filters.gmphd import GMPHD, MixtureState

    phd = GMPHD()
    state = MixtureState(torch.zeros(2), torch.zeros(2, 4), -10.0 * torch.eye(4).expand(2, 4, 4),
                         torch.arange(2), torch.ones(2, dtype=torch.bool))
    with pytest.raises(TorchtrackError, match=r"GMPHD update: innovation covariance S is not positive definite \(2 of"):
        phd.update(state, torch.zeros(1, 2), phd.matrices(1.0))
