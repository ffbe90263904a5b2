"""Resamplers: unbiased offspring counts, variance ordering, differentiable weights, bad input."""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.particle import resampling

W = torch.tensor([0.31, 0.02, 0.17, 0.0, 0.255, 0.105, 0.07, 0.07], dtype=torch.float64)
N, REPS = W.numel(), 20_000


def _counts(name: str, seed: int = 0) -> torch.Tensor:
    log_w = torch.log(W).expand(REPS, N)       # every row one independent repeat
    a = resampling.get_resampler(name)(log_w, torch.Generator().manual_seed(seed))
    assert a.shape == (REPS, N) and a.dtype == torch.long
    return resampling.offspring_counts(a, N).double()


@pytest.mark.parametrize("name", resampling.RESAMPLERS)
def test_expected_offspring_is_n_times_weight(name):
    counts = _counts(name)
    assert (counts.sum(-1) == N).all()
    expected = N * W
    se = torch.sqrt(N * W * (1 - W) / REPS)       # multinomial standard error bounds the others'
    assert ((counts.mean(0) - expected).abs() <= 4 * se + 1e-12).all()
    assert (counts[:, 3] == 0).all()              # a zero weight is never selected


@pytest.mark.parametrize("name", ["systematic", "stratified", "residual"])
def test_lower_variance_than_multinomial(name):
    var_multi = _counts("multinomial", 1).var(0).sum()
    assert _counts(name, 2).var(0).sum() < 0.5 * var_multi


def test_systematic_counts_are_floor_or_ceil():
    counts = _counts("systematic")
    nw = N * W
    assert ((counts >= torch.floor(nw)) & (counts <= torch.ceil(nw))).all()


def test_batched_rows_are_independent_and_reproducible():
    log_w = torch.randn(3, 5, 100, dtype=torch.float64)
    a1 = resampling.systematic(log_w, torch.Generator().manual_seed(7))
    a2 = resampling.systematic(log_w, torch.Generator().manual_seed(7))
    assert a1.shape == (3, 5, 100) and torch.equal(a1, a2)
    # each row follows its own weights: the heaviest particle of a row is selected in that row
    heavy = log_w.argmax(-1, keepdim=True)
    w_max = torch.softmax(log_w, -1).gather(-1, heavy)
    picked = (a1 == heavy).sum(-1, keepdim=True)
    assert (picked >= torch.floor(100 * w_max)).all()


def test_stop_gradient_weights_forward_and_gradient():
    """Forward: equal weights w̄; gradient of Σ w̃ averages to ∇ Σ w (Ścibior & Wood 2021)."""
    theta = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    x = torch.linspace(-2, 2, 16, dtype=torch.float64)
    log_w = -0.5 * (x - theta) ** 2
    a = resampling.multinomial(log_w.detach().expand(4000, 16), torch.Generator().manual_seed(0))
    new = resampling.resampled_log_weight(log_w.expand(4000, 16), a)
    mean_w = torch.logsumexp(log_w, -1) - math.log(16)
    assert torch.allclose(new, mean_w.detach().expand_as(new))
    (g,) = torch.autograd.grad(torch.logsumexp(new, -1).mean(), theta, retain_graph=True)
    (g_exact,) = torch.autograd.grad(torch.logsumexp(log_w, -1), theta)
    assert abs(g.item() - g_exact.item()) < 0.05 * abs(g_exact.item()) + 0.01


def test_soft_resampling_preserves_total_weight_in_expectation():
    log_w = torch.log(W).expand(REPS, N)
    log_q = resampling.soft_proposal(log_w, 0.5)
    assert torch.allclose(log_q.exp().sum(-1), torch.ones(REPS, dtype=torch.float64))
    a = resampling.systematic(log_q, torch.Generator().manual_seed(3))
    new = resampling.resampled_log_weight(log_w, a, log_q)
    total = torch.logsumexp(new, -1).exp()        # Σ w was 1
    assert abs(total.mean().item() - 1.0) < 0.01


def test_degenerate_row_resamples_uniformly():
    log_w = torch.full((2000, 5), -math.inf, dtype=torch.float64)
    for name in resampling.RESAMPLERS:
        a = resampling.get_resampler(name)(log_w, torch.Generator().manual_seed(0))
        counts = resampling.offspring_counts(a, 5).double().mean(0)
        assert torch.allclose(counts, torch.ones(5, dtype=torch.float64), atol=0.1), name


def test_unknown_resampler_and_bad_alpha_raise():
    with pytest.raises(TorchtrackError, match="resampler"):
        resampling.get_resampler("bogus")
    with pytest.raises(TorchtrackError, match="alpha"):
        resampling.soft_proposal(torch.zeros(3), 1.5)
