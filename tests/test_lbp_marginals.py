"""Loopy belief propagation against brute-force enumeration of all joint associations."""

from __future__ import annotations

import itertools

import pytest
import torch

from torchtrack.association.lbp import lbp_marginals
from torchtrack.errors import TorchtrackError

NEG = float("-inf")


def exact_marginals(log_w: torch.Tensor, log_miss: torch.Tensor, log_new: torch.Tensor):
    """Enumerate every association (track → miss or a distinct measurement); differentiable."""
    n, m = log_w.shape
    terms, assigns = [], []
    for a in itertools.product(range(-1, m), repeat=n):
        used = [j for j in a if j >= 0]
        if len(used) != len(set(used)):
            continue
        lw = sum((log_miss[i] if j < 0 else log_w[i, j]) for i, j in enumerate(a))
        lw = lw + sum(log_new[j] for j in range(m) if j not in used)
        terms.append(lw)
        assigns.append(a)
    logp = torch.stack(terms)
    p = torch.softmax(logp, 0)
    assoc = torch.zeros(n, m, dtype=log_w.dtype)
    miss = torch.zeros(n, dtype=log_w.dtype)
    new = torch.zeros(m, dtype=log_w.dtype)
    for k, a in enumerate(assigns):
        for i, j in enumerate(a):
            if j < 0:
                miss = miss + p[k] * torch.nn.functional.one_hot(torch.tensor(i), n).to(p)
            else:
                assoc = assoc + p[k] * torch.nn.functional.one_hot(torch.tensor(i * m + j), n * m).to(p).view(n, m)
        for j in range(m):
            if j not in a:
                new = new + p[k] * torch.nn.functional.one_hot(torch.tensor(j), m).to(p)
    return assoc, miss, new


def tree_problem(g: torch.Generator, n: int, m: int):
    """Each measurement may be taken by at most one track: the factor graph has no cycle."""
    owner = torch.randint(0, n, (m,), generator=g)
    log_w = torch.randn(n, m, generator=g, dtype=torch.float64) * 2
    mask = owner.unsqueeze(0) == torch.arange(n).unsqueeze(1)
    mask &= torch.rand(n, m, generator=g) < 0.8
    log_w = torch.where(mask, log_w, torch.full_like(log_w, NEG))
    return log_w, torch.randn(n, generator=g, dtype=torch.float64), torch.randn(m, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("seed", range(6))
def test_exact_on_problems_without_competition(seed):
    g = torch.Generator().manual_seed(seed)
    log_w, log_miss, log_new = tree_problem(g, 3, 4)
    res = lbp_marginals(log_w, log_miss, log_new, iterations=100, tol=1e-12)
    assoc, miss, new = exact_marginals(log_w, log_miss, log_new)
    torch.testing.assert_close(res.assoc, assoc, atol=1e-9, rtol=0)
    torch.testing.assert_close(res.miss, miss, atol=1e-9, rtol=0)
    torch.testing.assert_close(res.new, new, atol=1e-9, rtol=0)
    torch.testing.assert_close(res.meas_assoc, assoc, atol=1e-9, rtol=0)


@pytest.mark.parametrize("seed", range(6))
def test_close_on_loosely_coupled_problems(seed):
    """Every track has a strong own measurement; all other pairs are ~e^-4 weaker."""
    g = torch.Generator().manual_seed(100 + seed)
    n, m = 3, 4
    log_w = torch.randn(n, m, generator=g, dtype=torch.float64) - 4.0
    log_w[torch.arange(n), torch.arange(n)] = 2.0 + torch.rand(n, generator=g, dtype=torch.float64)
    log_miss = torch.zeros(n, dtype=torch.float64)
    log_new = torch.zeros(m, dtype=torch.float64)
    res = lbp_marginals(log_w, log_miss, log_new, iterations=200, tol=1e-12)
    assert res.converged
    assoc, miss, new = exact_marginals(log_w, log_miss, log_new)
    assert (res.assoc - assoc).abs().max() < 5e-3
    assert (res.miss - miss).abs().max() < 5e-3
    assert (res.new - new).abs().max() < 5e-3


def test_strongly_coupled_problem_is_approximate_but_valid():
    """Two tracks fighting over one measurement: LBP is not exact, but sensible."""
    log_w = torch.tensor([[1.0], [1.0]], dtype=torch.float64)
    res = lbp_marginals(log_w, torch.zeros(2, dtype=torch.float64), torch.zeros(1, dtype=torch.float64),
                        iterations=200, tol=1e-12)
    assoc, _, _ = exact_marginals(log_w, torch.zeros(2, dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
    assert abs(float(res.assoc[0, 0] - res.assoc[1, 0])) < 1e-12       # symmetric
    assert abs(float(res.assoc[0, 0] - assoc[0, 0])) < 0.1


def test_marginals_are_distributions_batched_with_padding():
    g = torch.Generator().manual_seed(7)
    B, n, m = 5, 12, 15
    log_w = torch.randn(B, n, m, generator=g, dtype=torch.float64) * 3
    log_w[torch.rand(B, n, m, generator=g) < 0.6] = NEG
    log_w[:, -2:, :] = NEG          # padding tracks
    log_w[:, :, -3:] = NEG          # padding measurements
    log_miss = torch.randn(B, n, generator=g, dtype=torch.float64)
    log_new = torch.randn(B, m, generator=g, dtype=torch.float64)
    res = lbp_marginals(log_w, log_miss, log_new, iterations=100)
    assert bool((res.assoc >= 0).all()) and bool((res.meas_assoc >= 0).all())
    torch.testing.assert_close(res.assoc.sum(-1) + res.miss, torch.ones(B, n, dtype=torch.float64))
    torch.testing.assert_close(res.meas_assoc.sum(-2) + res.new, torch.ones(B, m, dtype=torch.float64))
    torch.testing.assert_close(res.miss[:, -2:], torch.ones(B, 2, dtype=torch.float64))
    torch.testing.assert_close(res.new[:, -3:], torch.ones(B, 3, dtype=torch.float64))
    # padding does not change the real part, and the batch equals the items one by one
    for b in range(B):
        one = lbp_marginals(log_w[b, :-2, :-3], log_miss[b, :-2], log_new[b, :-3], iterations=100)
        torch.testing.assert_close(one.assoc, res.assoc[b, :-2, :-3], atol=1e-6, rtol=0)


def test_zero_miss_and_new_weights_stay_finite():
    """p_D = 1 with no clutter: miss and new-target weights are zero (log -inf)."""
    log_w = torch.tensor([[0.0, NEG], [NEG, -1.0]], dtype=torch.float64)
    res = lbp_marginals(log_w, torch.full((2,), NEG, dtype=torch.float64),
                        torch.full((2,), NEG, dtype=torch.float64))
    assert bool(torch.isfinite(res.assoc).all())
    torch.testing.assert_close(res.assoc, torch.eye(2, dtype=torch.float64), atol=1e-9, rtol=0)


def test_float32_matches_float64():
    g = torch.Generator().manual_seed(3)
    log_w = torch.randn(40, 50, generator=g, dtype=torch.float64) * 3
    log_w[torch.rand(40, 50, generator=g) < 0.8] = NEG
    lm, ln = torch.zeros(40, dtype=torch.float64), torch.zeros(50, dtype=torch.float64)
    r64 = lbp_marginals(log_w, lm, ln, iterations=30, tol=None)
    r32 = lbp_marginals(log_w.float(), lm.float(), ln.float(), iterations=30, tol=None)
    assert (r32.assoc.double() - r64.assoc).abs().max() < 1e-4


def test_gradients_through_fixed_iterations_match_exact_gradients():
    """On a cycle-free problem LBP is exact, so its gradient must equal the brute-force gradient."""
    g = torch.Generator().manual_seed(11)
    log_w, log_miss, log_new = tree_problem(g, 3, 3)
    target = torch.randn(3, 3, generator=g, dtype=torch.float64)

    def loss(fn):
        lw = log_w.clone().requires_grad_(True)
        lm = log_miss.clone().requires_grad_(True)
        a = fn(lw, lm)
        (a * target).sum().backward()
        return lw.grad, lm.grad

    gw, gm = loss(lambda lw, lm: lbp_marginals(lw, lm, log_new, iterations=60, tol=None).assoc)
    ew, em = loss(lambda lw, lm: exact_marginals(lw, lm, log_new)[0])
    finite = torch.isfinite(log_w)
    assert bool(gw[finite].abs().sum() > 0)
    torch.testing.assert_close(gw[finite], ew[finite], atol=1e-8, rtol=0)
    torch.testing.assert_close(gm, em, atol=1e-8, rtol=0)


def test_gradcheck_on_a_loopy_problem():
    g = torch.Generator().manual_seed(5)
    log_w = torch.randn(3, 4, generator=g, dtype=torch.float64, requires_grad=True)
    log_miss = torch.randn(3, generator=g, dtype=torch.float64, requires_grad=True)
    log_new = torch.randn(4, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda a, b, c: lbp_marginals(a, b, c, iterations=8, tol=None).assoc, (log_w, log_miss, log_new))


def test_bad_input_is_a_clear_error():
    with pytest.raises(TorchtrackError, match="log_w"):
        lbp_marginals(torch.tensor([[float("nan")]]), torch.zeros(1), torch.zeros(1))
    with pytest.raises(TorchtrackError, match="log_miss"):
        lbp_marginals(torch.zeros(2, 3), torch.zeros(3), torch.zeros(3))
    with pytest.raises(TorchtrackError, match="iterations"):
        lbp_marginals(torch.zeros(2, 3), torch.zeros(2), torch.zeros(3), iterations=0)


def test_empty_problems():
    res = lbp_marginals(torch.zeros(4, 0), torch.zeros(4), torch.zeros(0))
    torch.testing.assert_close(res.miss, torch.ones(4))
    res = lbp_marginals(torch.zeros(0, 3), torch.zeros(0), torch.zeros(3))
    torch.testing.assert_close(res.new, torch.ones(3))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_two_pairs_of_one_track_keep_their_ratio(dtype):
    """One track, likelihoods 1 and 2, clutter 0.1 each, miss weight 0: exactly [1/3, 2/3] (a cap on
    log ψ made both pairs equal)."""
    log_w = torch.tensor([[1.0, 2.0]], dtype=torch.float64).log()
    log_miss = torch.tensor([NEG], dtype=torch.float64)
    log_new = torch.tensor([0.1, 0.1], dtype=torch.float64).log()
    assoc, miss, new = exact_marginals(log_w, log_miss, log_new)
    torch.testing.assert_close(assoc, torch.tensor([[1 / 3, 2 / 3]], dtype=torch.float64), atol=1e-15, rtol=0)
    res = lbp_marginals(log_w.to(dtype), log_miss.to(dtype), log_new.to(dtype))
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(res.assoc.double(), assoc, atol=tol, rtol=0)
    torch.testing.assert_close(res.meas_assoc.double(), assoc, atol=tol, rtol=0)
    torch.testing.assert_close(res.miss.double(), miss, atol=tol, rtol=0)
    torch.testing.assert_close(res.new.double(), new, atol=tol, rtol=0)


def test_float32_pedestrian_magnitudes_match_enumeration():
    """The pedestrian config's magnitudes (miss 0.1, clutter density 6.25e-5, likelihoods 1.44 and 0.72),
    in float32 as ``bench pmb --dtype float32`` runs them."""
    log_w = torch.tensor([[1.44, 0.72]], dtype=torch.float64).log()
    log_miss = torch.tensor([0.1], dtype=torch.float64).log()
    log_new = torch.tensor([6.25e-5, 6.25e-5], dtype=torch.float64).log()
    assoc, miss, new = exact_marginals(log_w, log_miss, log_new)
    res = lbp_marginals(log_w.float(), log_miss.float(), log_new.float())
    assert res.assoc.dtype == torch.float32
    torch.testing.assert_close(res.assoc.double(), assoc, atol=1e-6, rtol=0)
    torch.testing.assert_close(res.meas_assoc.double(), assoc, atol=1e-6, rtol=0)
    torch.testing.assert_close(res.miss.double(), miss, rtol=1e-5, atol=0)
    torch.testing.assert_close(res.new.double(), new, atol=1e-6, rtol=0)


def _relative_close(actual: torch.Tensor, expected: torch.Tensor, rtol: float) -> None:
    """Every probability to ``rtol`` of itself (the small ones too), zeros exact."""
    torch.testing.assert_close(actual.double(), expected, rtol=rtol, atol=0)


@pytest.mark.parametrize("autograd", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forest_at_extreme_magnitudes(dtype, autograd):
    """A tree (track 0 - z0 - track 1, track 0 - z1) where track 0 is e^40 times surer of z0 than of
    anything else: the remainder of its dominant term is 2e-35 of the sum, below float64's epsilon,
    and track 1's marginals hinge on it. Every marginal, small ones included, to a few rounding errors,
    in the in-place iteration and in the differentiable one (inputs that require gradients)."""
    log_w = torch.tensor([[40.0, 0.0], [40.0, NEG]], dtype=torch.float64)
    log_miss = torch.tensor([0.0, 0.0], dtype=torch.float64)
    log_new = torch.tensor([0.0, 0.0], dtype=torch.float64)
    assoc, miss, new = exact_marginals(log_w, log_miss, log_new)
    assert 0.3 < float(assoc[1, 0]) < 0.7                   # the answer is not saturated
    res = lbp_marginals(log_w.to(dtype).requires_grad_(autograd), log_miss.to(dtype), log_new.to(dtype),
                        iterations=20)
    res = res._replace(**{k: getattr(res, k).detach() for k in ("assoc", "miss", "new", "meas_assoc")})
    rtol = 1e-5 if dtype == torch.float32 else 1e-12
    _relative_close(res.assoc, assoc, rtol)
    _relative_close(res.meas_assoc, assoc, rtol)
    _relative_close(res.miss, miss, rtol)
    _relative_close(res.new, new, rtol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(4))
def test_random_forests_at_large_magnitudes(dtype, seed):
    """Cycle-free problems with log weights spread over ±60 and some zero miss weights: exact."""
    g = torch.Generator().manual_seed(200 + seed)
    log_w, log_miss, log_new = tree_problem(g, 3, 4)
    log_w = log_w * 15
    log_miss = torch.where(torch.rand(3, generator=g) < 0.3, torch.full_like(log_miss, NEG), log_miss * 15)
    log_new = log_new * 15
    assoc, miss, new = exact_marginals(log_w, log_miss, log_new)
    res = lbp_marginals(log_w.to(dtype), log_miss.to(dtype), log_new.to(dtype), iterations=20)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for got, want in ((res.assoc, assoc), (res.meas_assoc, assoc), (res.miss, miss), (res.new, new)):
        torch.testing.assert_close(got.double(), want, atol=tol, rtol=0)
