"""Detection without whole-frame float buffers (issue #28): windows normalised as they are read equal the old
whole-frame normalisation, and peaks decoded block by block equal the whole map's decoding."""

import pytest
import torch

from torchtrack.detector.decode import TopPeaks, decode
from torchtrack.detector.normalised import NormalisedFrame, frame_stats


def _old_normalise(frame: torch.Tensor) -> torch.Tensor:
    """The whole-frame path this replaces: one float32 copy, torch's float32 mean and std."""
    f = frame.to(torch.float32, copy=True)
    return f.sub_(f.mean()).div_(f.std() + 1.0)


def test_uint8_statistics_are_exact():
    g = torch.Generator().manual_seed(0)
    frame = (torch.rand(301, 1117, generator=g) * 256).to(torch.uint8)   # several chunks of rows
    mean, std = frame_stats(frame)
    f = frame.double()
    assert mean.dtype == std.dtype == torch.float32
    assert mean == f.mean().float() and std == f.std().float()


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float64])
def test_windows_and_patches_equal_the_whole_frame_normalisation(dtype):
    g = torch.Generator().manual_seed(1)
    frame = (torch.rand(200, 333, generator=g, dtype=torch.float64) * 255).to(dtype)
    old = _old_normalise(frame)
    norm = NormalisedFrame(frame)
    if dtype == torch.uint8:
        assert norm.mean == frame.float().mean()    # this frame's float32 mean is exact: bit-equal windows
    assert torch.equal(norm[:, :], old)
    assert torch.equal(norm[17:150, 40:301], old[17:150, 40:301])
    ys, xs = torch.randint(0, 200, (50, 1), generator=g), torch.randint(0, 333, (1, 7), generator=g)
    assert torch.equal(norm[ys, xs], old[ys, xs])
    band = norm.rows(64, 128)
    assert band.shape == (64, 333) and torch.equal(band[:, 5:9], old[64:128, 5:9])


def _blocks(h: int, w: int, cuts_y: list[int], cuts_x: list[int]):
    """Blocks of an (h, w) map: cores on the grid of cuts, each with its ring of neighbours inside the map."""
    for y0, y1 in zip([0, *cuts_y], [*cuts_y, h]):
        for x0, x1 in zip([0, *cuts_x], [*cuts_x, w]):
            by, bx = max(y0 - 1, 0), max(x0 - 1, 0)
            yield (slice(by, min(y1 + 1, h)), slice(bx, min(x1 + 1, w))), (by, bx), (y0 - by, y1 - by, x0 - bx, x1 - bx)


@pytest.mark.parametrize("threshold, cap", [(0.3, 10_000), (0.3, 40), (0.0, 25)])
def test_peaks_decoded_block_by_block_equal_the_whole_maps(threshold, cap):
    g = torch.Generator().manual_seed(2)
    h, w = 61, 77
    logits = (torch.randn(h, w, generator=g) * 2).round()   # few distinct values: ties and plateaus everywhere
    logits[10:13, 30:34] = 3.0                              # a plateau across a block seam
    maps = torch.cat([logits[None], torch.rand(2, h, w, generator=g), torch.randn(2, h, w, generator=g)])
    whole = decode(maps[None, :1], maps[None, 1:3], maps[None, 3:], 2, threshold, cap)
    keep = whole.mask[0]
    peaks = TopPeaks(cap, w, 2, threshold)
    for (rows, cols), origin, own in _blocks(h, w, [12, 40], [11, 33, 60]):
        peaks.add(maps[:, rows, cols], origin, own)
    got = peaks.detections()
    assert len(got.xy) == int(keep.sum()) > 20
    assert (len(got.xy) == cap) == (cap < 1000)             # the cap binds in the small-cap cases
    assert torch.equal(got.xy, whole.xy[0, keep])           # the same peaks in the same order, ties included
    assert torch.equal(got.score, whole.score[0, keep])
    assert torch.equal(got.velocity, whole.velocity[0, keep])
