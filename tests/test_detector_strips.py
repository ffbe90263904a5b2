"""Detection over horizontal strips (issue #28 item 5): strips that partition a frame give, together, the whole
frame's detections — each strip computed from its rows and a halo only."""

import dataclasses

import pytest
import torch

from torchtrack.detector import inference
from torchtrack.detector.inference import load_detector
from torchtrack.errors import TorchtrackError

H, W = 420, 610
SEAMS = (144, 208, 288)


def make_scene():
    """A textured frame with bright blobs (several centred on the seams), the previous frame (moved by 3 px),
    and a prior with velocities on some of the blobs."""
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    cur = torch.rand(H, W, generator=g, dtype=torch.float64) * 12 + 60
    centres = torch.rand(120, 2, generator=g, dtype=torch.float64) * torch.tensor([W - 10.0, H - 10.0]) + 5
    on_seams = torch.tensor([[40.0 + 90 * i, s + (i % 3 - 1) * 0.7] for i, s in enumerate(SEAMS * 2)])
    centres = torch.cat([on_seams.double(), centres])
    yy, xx = torch.meshgrid(torch.arange(float(H)), torch.arange(float(W)), indexing="ij")
    for x, y in centres:
        cur += 150 * torch.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 4.0)
    prev = torch.roll(cur, 3, dims=1)
    return cur, prev, centres[:40].float(), torch.full((40, 2), 3.0)


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def _with_tile(det, tile: int):
    det.config = dataclasses.replace(det.config, decode=dataclasses.replace(det.config.decode, tile=tile))
    return det


def _union(parts):
    """The strips' detections in the whole frame's decoding order: best score first, equal scores by strip."""
    xy, score, velocity = (torch.cat([getattr(p, f) for p in parts]) for f in ("xy", "score", "velocity"))
    order = torch.argsort(-score.double(), stable=True)
    return xy[order], score[order], velocity[order]


@pytest.mark.parametrize("tile", [0, 128])
@pytest.mark.parametrize("cuts", [(0, 208, H), (0, 144, 288, H), (0, 16, 400, H)])
def test_strips_together_are_the_whole_frames_detections(scene, tile, cuts):
    cur, prev, prior, prior_velocity = scene
    det = _with_tile(load_detector(), tile)
    whole = det.detect(cur, prev, prior, prev_velocity=prior_velocity)
    parts = [det.detect(cur, prev, prior, prev_velocity=prior_velocity, rows=(a, b)) for a, b in zip(cuts, cuts[1:])]
    xy, score, velocity = _union(parts)
    assert len(whole.xy) > 100 and len(xy) == len(whole.xy)
    torch.testing.assert_close(xy, whole.xy, rtol=0, atol=1e-5)
    torch.testing.assert_close(score, whole.score, rtol=0, atol=1e-5)
    torch.testing.assert_close(velocity, whole.velocity, rtol=0, atol=1e-5)
    # each strip holds the blobs whose cell lies in its rows; a blob on a seam is found once, by one strip
    for (a, b), p in zip(zip(cuts, cuts[1:]), parts):
        assert ((p.xy[:, 1] > a - 2) & (p.xy[:, 1] < b + 2)).all()
    for x, y in torch.tensor([[40.0 + 90 * i, s] for i, s in enumerate(SEAMS * 2)]):
        assert ((xy - torch.tensor([x, y])).norm(dim=1) < 4).sum() == 1


def test_a_halo_short_of_the_receptive_field_changes_a_strip(scene, monkeypatch):
    cur, prev, prior, _ = scene
    det = _with_tile(load_detector(), 0)
    inputs = det.inputs(cur, prev, prior)
    maps, own, first = det.strip_maps(*inputs, (208, H))
    whole = det.maps(*inputs)
    torch.testing.assert_close(maps, whole[:, first: first + maps.shape[1]], rtol=0, atol=1e-4)
    assert own == (104 - first, (H + 1) // 2 - first) and first == 103
    monkeypatch.setattr(inference, "HALO", 16)
    short, _, first = det.strip_maps(*inputs, (208, H))
    assert (short - whole[:, first: first + short.shape[1]]).abs().max() > 1e-2


@pytest.mark.parametrize("rows", [(8, 208), (0, 200), (208, 208), (0, H + 16), (-16, 64)])
def test_strip_rows_off_the_stride_or_outside_the_frame_are_refused(scene, rows):
    cur, prev, prior, _ = scene
    with pytest.raises(TorchtrackError, match="rows"):
        load_detector().detect(cur, prev, prior, rows=rows)
