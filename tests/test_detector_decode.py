"""Decoding finds planted peaks exactly; targets -> decode round trip; heatmap rendering; focal loss."""

import math

import numpy as np
import torch

from torchtrack.detector.decode import decode
from torchtrack.detector.losses import focal_loss
from torchtrack.detector.targets import gaussian_heatmap, make_targets


def test_decode_finds_planted_peaks_and_offsets():
    h, w, stride = 20, 24, 2
    logits = torch.full((1, 1, h, w), -8.0)
    off = torch.zeros(1, 2, h, w)
    vel = torch.zeros(1, 2, h, w)
    cells = [(3, 4, 0.25, 0.75, 1.5, -2.0), (10, 10, 0.0, 0.5, 0.0, 3.0), (20, 17, 0.875, 0.125, -7.0, 0.25)]
    for cx, cy, ox, oy, vx, vy in cells:
        logits[0, 0, cy, cx] = 3.0
        off[0, :, cy, cx] = torch.tensor([ox, oy])
        vel[0, :, cy, cx] = torch.tensor([vx, vy])
    logits[0, 0, 4, 4] = 2.0          # a lower neighbour of the first peak: suppressed by the 3x3 max-pool
    logits[0, 0, 15, 2] = -1.5        # an isolated peak below the threshold (sigmoid 0.18 < 0.3)
    det = decode(logits, off, vel, stride, threshold=0.3, top_k=50)
    xy = det.xy[0][det.mask[0]].numpy()
    v = det.velocity[0][det.mask[0]].numpy()
    assert det.mask.sum() == 3
    expect = np.array([[(cx + ox) * stride, (cy + oy) * stride] for cx, cy, ox, oy, _, _ in cells])
    order = np.lexsort((xy[:, 1], xy[:, 0]))
    eorder = np.lexsort((expect[:, 1], expect[:, 0]))
    np.testing.assert_array_equal(xy[order], expect[eorder])
    np.testing.assert_array_equal(v[order], np.array([c[4:] for c in cells])[eorder])
    np.testing.assert_allclose(det.score[0][det.mask[0]].numpy(), 1 / (1 + math.exp(-3.0)), rtol=1e-6)


def test_targets_decode_round_trip():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(30, 2, generator=g) * torch.tensor([62.0, 46.0])
    # keep points at least 5 px apart so that each owns its peak
    keep = [0]
    for i in range(1, len(pts)):
        if torch.cdist(pts[i:i + 1], pts[keep]).min() > 5:
            keep.append(i)
    pts = pts[keep]
    vel = torch.randn(len(pts), 2, generator=g) * 5
    t = make_targets(pts, vel, (48, 64), 2, 0.8)
    logits = torch.logit(t.heatmap.clamp(1e-4, 1 - 1e-4))[None]
    det = decode(logits, t.offset[None], t.velocity[None], 2, threshold=0.99, top_k=100)
    got = det.xy[0][det.mask[0]]
    assert len(got) == len(pts)
    d = torch.cdist(got, pts)
    assert d.min(dim=1).values.max() < 1e-5
    np.testing.assert_allclose(det.velocity[0][det.mask[0]].numpy(), vel[d.argmin(dim=1)].numpy(), atol=1e-5)


def test_gaussian_heatmap_matches_brute_force():
    pts = torch.tensor([[3.3, 4.7], [10.0, 2.0], [0.2, 11.6]])
    hm = gaussian_heatmap(pts, (12, 14), 1.2)
    yy, xx = np.mgrid[0:12, 0:14]
    ref = np.max([np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2 ** 2)) * (np.abs(xx - round(x)) <= 4)
                  * (np.abs(yy - round(y)) <= 4) for x, y in pts.tolist()], axis=0)
    np.testing.assert_allclose(hm.numpy(), ref, atol=1e-6)


def test_focal_loss_matches_formula():
    g = torch.Generator().manual_seed(1)
    logits = torch.randn(2, 1, 5, 6, generator=g, dtype=torch.float64)
    target = torch.rand(2, 1, 5, 6, generator=g, dtype=torch.float64) * 0.9
    target[0, 0, 1, 2] = 1.0
    target[0, 0, 3, 3] = 1.0
    got = focal_loss(logits, target)
    p = torch.sigmoid(logits).numpy()
    y = target.numpy()
    for b in range(2):
        pos = y[b] == 1
        s = np.sum((1 - p[b][pos]) ** 2 * np.log(p[b][pos]))
        s += np.sum((1 - y[b][~pos]) ** 4 * p[b][~pos] ** 2 * np.log(1 - p[b][~pos]))
        np.testing.assert_allclose(got[b].item(), -s / max(1, pos.sum()), rtol=1e-10)


def test_decode_matches_a_dense_max_pool_reference():
    from torch.nn import functional as F

    g = torch.Generator().manual_seed(1)
    logits = torch.randn(3, 1, 30, 34, generator=g) * 2 - 1
    logits[1, 0, 5:8, 5:8] = 2.5                      # a plateau: every cell equals its 3x3 maximum
    off, vel = torch.rand(3, 2, 30, 34, generator=g), torch.randn(3, 2, 30, 34, generator=g)
    for thr, top_k in [(0.3, 1000), (0.6, 7), (0.0, 50)]:
        det = decode(logits, off, vel, 2, threshold=thr, top_k=top_k)
        score = torch.sigmoid(logits)
        peak = (F.max_pool2d(score, 3, 1, 1) == score) & (score > thr)
        for b in range(3):
            ys, xs = torch.nonzero(peak[b, 0], as_tuple=True)
            s = score[b, 0, ys, xs]
            best = torch.argsort(-s)[:top_k]
            assert int(det.mask[b].sum()) == len(best)
            got = {(round(x, 4), round(y, 4)) for x, y in det.xy[b][det.mask[b]].tolist()}
            want = {(round(float((xs[i] + off[b, 0, ys[i], xs[i]]) * 2), 4),
                     round(float((ys[i] + off[b, 1, ys[i], xs[i]]) * 2), 4)) for i in best}
            if len(best) < len(s) and torch.sort(-s).values[top_k - 1] == torch.sort(-s).values[top_k]:
                continue                              # a tie at the cut: either peak may be kept
            assert got == want
            sc = det.score[b][det.mask[b]]
            assert torch.all(sc[:-1] >= sc[1:])       # best first


def test_the_peak_cap_grows_with_the_frame_area():
    """``top_k`` holds for frames up to 512²; a 2048² frame (16 times the area) may keep 16 times the peaks."""
    from torchtrack.detector.config import DecodeConfig

    cfg = DecodeConfig(top_k=1000)
    assert [cfg.peaks_for(*s) for s in [(64, 64), (512, 512), (1024, 512), (2048, 2048)]] == [1000, 1000, 2000, 16000]
