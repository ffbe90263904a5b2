"""Loopy belief propagation on the gated pairs equals the dense ``n × m`` version (float64, to 1e-10)."""

from __future__ import annotations

import pytest
import torch

from torchtrack.association.lbp import lbp_marginals
from torchtrack.association.lbp_sparse import sparse_lbp_marginals
from torchtrack.errors import TorchtrackError

NEG_INF = float("-inf")


def _problem(seed: int, density: float = 0.2):
    g = torch.Generator().manual_seed(seed)
    n, m = (int(v) for v in torch.randint(1, 40, (2,), generator=g))
    log_w = 4.0 * torch.randn(n, m, generator=g, dtype=torch.float64)
    log_w[torch.rand(n, m, generator=g) > density] = NEG_INF
    log_miss = 3.0 * torch.randn(n, generator=g, dtype=torch.float64)
    log_miss[0] = NEG_INF                                   # a track that cannot miss (p_D = 1, r = 1)
    log_new = 3.0 * torch.randn(m, generator=g, dtype=torch.float64)
    return log_w, log_miss, log_new


@pytest.mark.parametrize("tol", [None, 1e-9])
@pytest.mark.parametrize("seed", range(12))
def test_sparse_marginals_equal_the_dense_ones(seed, tol):
    log_w, log_miss, log_new = _problem(seed)
    dense = lbp_marginals(log_w, log_miss, log_new, iterations=40, tol=tol)
    row, col = torch.isfinite(log_w).nonzero().unbind(1)
    sparse = sparse_lbp_marginals(row, col, log_w[row, col], log_miss, log_new, iterations=40, tol=tol)
    assert sparse.iterations == dense.iterations
    for got, want in ((sparse.assoc, dense.assoc[row, col]), (sparse.meas_assoc, dense.meas_assoc[row, col]),
                      (sparse.miss, dense.miss), (sparse.new, dense.new)):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-10)
    # rows and columns are distributions
    n, m = log_w.shape
    row_sum = sparse.miss + torch.zeros(n, dtype=torch.float64).index_add(0, row, sparse.assoc)
    col_sum = sparse.new + torch.zeros(m, dtype=torch.float64).index_add(0, col, sparse.meas_assoc)
    torch.testing.assert_close(row_sum, torch.ones(n, dtype=torch.float64), rtol=0, atol=1e-12)
    torch.testing.assert_close(col_sum, torch.ones(m, dtype=torch.float64), rtol=0, atol=1e-12)


def test_gradients_equal_the_dense_ones():
    log_w, log_miss, log_new = _problem(3, density=0.3)
    row, col = torch.isfinite(log_w).nonzero().unbind(1)
    target = torch.randn(row.shape[0], dtype=torch.float64)
    grads = []
    for sparse in (False, True):
        w = log_w[row, col].clone().requires_grad_(True)
        miss, new = log_miss.clone().requires_grad_(True), log_new.clone().requires_grad_(True)
        if sparse:
            res = sparse_lbp_marginals(row, col, w, miss, new, iterations=15, tol=None)
            assoc = res.assoc
        else:
            full = torch.full_like(log_w, NEG_INF).index_put((row, col), w)
            res = lbp_marginals(full, miss, new, iterations=15, tol=None)
            assoc = res.assoc[row, col]
        ((assoc * target).sum() + res.miss.sum() * 0.3 + (res.new ** 2).sum()).backward()
        grads.append((w.grad, miss.grad, new.grad))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)


def test_no_pairs_means_every_track_misses_and_every_measurement_is_new():
    empty = torch.zeros(0, dtype=torch.long)
    res = sparse_lbp_marginals(empty, empty, torch.zeros(0, dtype=torch.float64),
                               torch.tensor([-1.0, NEG_INF], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    assert res.miss.tolist() == [1.0, 1.0] and res.new.tolist() == [1.0, 1.0, 1.0] and res.assoc.numel() == 0


def test_bad_input_is_an_error():
    row = torch.tensor([0, 2])
    col = torch.tensor([0, 0])
    w = torch.zeros(2, dtype=torch.float64)
    with pytest.raises(TorchtrackError, match="out of range"):
        sparse_lbp_marginals(row, col, w, torch.zeros(2, dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
    with pytest.raises(TorchtrackError, match="NaN"):
        sparse_lbp_marginals(row[:1], col[:1], w[:1] * float("nan"), torch.zeros(1, dtype=torch.float64),
                             torch.zeros(1, dtype=torch.float64))
    with pytest.raises(TorchtrackError, match="iterations"):
        sparse_lbp_marginals(row[:1], col[:1], w[:1], torch.zeros(1, dtype=torch.float64),
                             torch.zeros(1, dtype=torch.float64), iterations=0)
