"""Soft GOSPA (Sinkhorn) loss: agreement with exact GOSPA, gradients against finite differences."""

import itertools
import math

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.metrics.ospa import gospa
from torchtrack.tuning.losses import sinkhorn_gospa


def brute_gospa(x: torch.Tensor, y: torch.Tensor, c: float, p: float) -> float:
    """GOSPA (alpha = 2) by enumerating every partial assignment — an independent reference."""
    N, M = x.shape[0], y.shape[0]
    best = math.inf
    small, large, swap = (x, y, False) if N <= M else (y, x, True)
    for k in range(small.shape[0] + 1):
        for rows in itertools.combinations(range(small.shape[0]), k):
            for cols in itertools.permutations(range(large.shape[0]), k):
                cost = sum(min(float((small[i] - large[j]).norm()), c) ** p for i, j in zip(rows, cols))
                cost += c**p / 2 * (N + M - 2 * k)
                best = min(best, cost)
    return best ** (1 / p)


@pytest.mark.parametrize("N,M", [(3, 2), (2, 4), (0, 3), (3, 0)])
def test_exact_gospa_matches_brute_force(N, M):   # the reference the soft GOSPA tends to
    g = torch.Generator().manual_seed(N * 10 + M)
    x = torch.randn(N, 2, generator=g, dtype=torch.float64) * 8
    y = torch.randn(M, 2, generator=g, dtype=torch.float64) * 8
    assert float(gospa(x, y, c=10.0).total) == pytest.approx(brute_gospa(x, y, 10.0, 2.0), rel=1e-12)


def test_sinkhorn_gospa_tends_to_exact_gospa():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(4, 2, generator=g, dtype=torch.float64) * 8
    y = torch.randn(3, 2, generator=g, dtype=torch.float64) * 8
    exact = brute_gospa(x, y, 10.0, 2.0)
    errs = [abs(sinkhorn_gospa(x, y, c=10.0, eps=eps, iters=2000).item() ** 0.5 - exact) for eps in (0.1, 0.02, 0.005)]
    assert errs[-1] < 0.01 * exact
    assert errs[0] > errs[-1]


def test_sinkhorn_gospa_masks_and_weights_equal_the_subsets():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(5, 2, generator=g, dtype=torch.float64) * 8
    y = torch.randn(4, 2, generator=g, dtype=torch.float64) * 8
    w = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0], dtype=torch.float64)
    mask = torch.tensor([True, True, False, True])
    soft = sinkhorn_gospa(x, y, est_weight=w, truth_mask=mask, c=10.0, eps=0.01, iters=1000).item() ** 0.5
    assert soft == pytest.approx(brute_gospa(x[w > 0], y[mask], 10.0, 2.0), rel=0.01)
    # batched call equals the unbatched ones
    xb = torch.stack([x, x.flip(0)])
    yb = torch.stack([y, y + 1])
    out = sinkhorn_gospa(xb, yb, c=10.0)
    assert out[1].item() == pytest.approx(sinkhorn_gospa(x.flip(0), y + 1, c=10.0).item(), rel=1e-12)
    assert sinkhorn_gospa(x[:0], y[:0]).item() == pytest.approx(0.0, abs=1e-12)


def test_sinkhorn_gospa_gradient_matches_finite_differences():
    g = torch.Generator().manual_seed(3)
    x = (torch.randn(3, 2, generator=g, dtype=torch.float64) * 5).requires_grad_()
    w = torch.tensor([0.9, 0.6, 0.3], dtype=torch.float64, requires_grad=True)
    y = torch.randn(2, 2, generator=g, dtype=torch.float64) * 5
    assert torch.autograd.gradcheck(lambda a, b: sinkhorn_gospa(a, y, est_weight=b, c=10.0, eps=0.1, iters=30),
                                    (x, w), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_sinkhorn_gospa_bad_input():
    with pytest.raises(TorchtrackError, match="same dimension"):
        sinkhorn_gospa(torch.zeros(2, 2), torch.zeros(2, 3))
    with pytest.raises(TorchtrackError, match="eps > 0"):
        sinkhorn_gospa(torch.zeros(2, 2), torch.zeros(2, 2), eps=0.0)
