"""Network pieces: the correlation layer against brute force, output shapes and the heatmap bias."""

import math

import numpy as np
import torch

from detector.network import STRIDE, CenterTrackNet, correlation


def test_correlation_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    b = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    r = 2
    got = correlation(a, b, r).numpy()
    an, bn = a.numpy(), b.numpy()
    ref = np.zeros((2, (2 * r + 1) ** 2, 5, 6))
    for n in range(2):
        for k, (dy, dx) in enumerate((dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)):
            for y in range(5):
                for x in range(6):
                    if 0 <= y + dy < 5 and 0 <= x + dx < 6:
                        ref[n, k, y, x] = an[n, :, y, x] @ bn[n, :, y + dy, x + dx] / 3
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)


def test_output_shapes_and_initial_heatmap():
    net = CenterTrackNet(widths=(8, 8, 8), head=8, motion=4, radius=2).eval()
    x = torch.randn(2, 3, 64, 96)
    with torch.no_grad():
        hm, off, vel = net(x)
    assert hm.shape == (2, 1, 64 // STRIDE, 96 // STRIDE)
    assert off.shape == vel.shape == (2, 2, 64 // STRIDE, 96 // STRIDE)
    # bias -4.6: initial scores about 0.01 (CenterNet's focal-loss initialisation)
    assert abs(torch.sigmoid(hm).mean().item() - 0.01) < 0.005
    assert math.isclose(net.heads.bias[0].item(), -math.log(99), rel_tol=1e-6)
