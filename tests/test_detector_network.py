"""Network pieces: the correlation layer against brute force, output shapes, the heatmap bias and the
stride-2 branch."""

import math

import numpy as np
import pytest
import torch

from torchtrack.detector.network import STRIDE, CenterTrackNet, correlation


@pytest.mark.parametrize("autograd", [False, True])
def test_correlation_matches_brute_force(autograd):
    g = torch.Generator().manual_seed(0)
    a = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    b = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    r = 2
    got = correlation(a.requires_grad_(autograd), b, r).detach().numpy()   # autograd: stacked path
    an, bn = a.detach().numpy(), b.numpy()
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


def test_fine_branch_starts_at_zero_and_reaches_the_heatmap():
    torch.manual_seed(0)
    net = CenterTrackNet(widths=(8, 8, 8), head=8, motion=4, radius=2, fine=4)
    x = torch.randn(2, 3, 64, 96)
    hm, off, vel = net(x)
    assert hm.shape == (2, 1, 32, 48) and off.shape == vel.shape == (2, 2, 32, 48)
    # the residual starts near zero: the initial scores are still about 0.01
    assert abs(torch.sigmoid(hm).mean().item() - 0.01) < 0.005
    # the branch is wired to the heatmap and the offset, not to the velocity
    (g_hm,) = torch.autograd.grad(hm.sum(), net.fine_in.weight, retain_graph=True)
    (g_off,) = torch.autograd.grad(off.sum(), net.fine_in.weight, retain_graph=True)
    g_vel = torch.autograd.grad(vel.sum(), net.fine_in.weight, allow_unused=True)[0]
    assert g_hm.abs().sum() > 0 and g_off.abs().sum() > 0
    assert g_vel is None or g_vel.abs().sum() == 0
    # a stride-2 feature: one input pixel moves the heatmap residual only within the 3x3 output cells
    # around it (the context path sees it too, through the stride-4 trunk; compare the branch alone)
    with torch.no_grad():
        y = x.clone()
        y[0, 0, 31, 41] += 5.0
        r0 = net.fine_out(torch.relu(net.fine_in(x)))
        r1 = net.fine_out(torch.relu(net.fine_in(y)))
    changed = (r1 - r0).abs().sum((0, 1)) > 0
    rows, cols = torch.nonzero(changed, as_tuple=True)
    assert rows.min() >= 15 - 1 and rows.max() <= 16 + 1 and cols.min() >= 20 - 1 and cols.max() <= 21 + 1
