"""Tiled inference (issue #28): a frame run in tiles gives the whole frame's maps and detections."""

import dataclasses

import pytest
import torch

from torchtrack.detector import inference
from torchtrack.detector.config import DecodeConfig
from torchtrack.detector.inference import load_detector
from torchtrack.errors import TorchtrackError


def _with_tile(det, tile: int):
    det.config = dataclasses.replace(det.config, decode=dataclasses.replace(det.config.decode, tile=tile))
    return det


def test_tiles_give_the_whole_frames_maps_and_detections(monkeypatch):
    torch.manual_seed(0)
    det = load_detector()
    g = torch.Generator().manual_seed(1)
    # an odd-sized textured frame with bright blobs that moved by 3 px, and a prior on some of them
    cur = torch.rand(420, 610, generator=g) * 60 + 40
    centres = torch.rand(60, 2, generator=g) * torch.tensor([600.0, 410.0])
    yy, xx = torch.meshgrid(torch.arange(420.0), torch.arange(610.0), indexing="ij")
    for x, y in centres:
        cur += 150 * torch.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 4.0)
    prev = torch.roll(cur, 3, dims=1)
    prior = centres[:20]
    whole = _with_tile(det, 0).detect(cur, prev, prior)
    maps_whole = det.maps(*det.inputs(cur, prev, prior))
    tiled = _with_tile(det, 128).detect(cur, prev, prior)          # 4 × 5 tiles of 128 px cores
    maps_tiled = det.maps(*det.inputs(cur, prev, prior))
    assert len(whole.xy) > 20
    torch.testing.assert_close(maps_tiled, maps_whole, rtol=0, atol=1e-4)
    torch.testing.assert_close(tiled.xy, whole.xy, rtol=0, atol=1e-4)
    torch.testing.assert_close(tiled.velocity, whole.velocity, rtol=0, atol=1e-4)
    # a halo shorter than the receptive field does change the maps: the comparison above can fail
    monkeypatch.setattr(inference, "HALO", 16)
    assert (det.maps(*det.inputs(cur, prev, prior)) - maps_whole).abs().max() > 1e-2


def test_a_tile_off_the_network_stride_is_refused():
    with pytest.raises(TorchtrackError, match="tile"):
        DecodeConfig(tile=1000)
