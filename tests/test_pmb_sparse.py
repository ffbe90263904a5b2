"""The PMB update on the gated pairs only equals the dense ``N × M`` update (float64, to 1e-10)."""

from __future__ import annotations

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb.filter import PMBFilter
from torchtrack.models import ConstantVelocity, LinearPosition

SIDE = 200.0


def _filter(sparse: bool, dims: int = 2) -> PMBFilter:
    return PMBFilter(ConstantVelocity(dims, q=1.0, learnable=False), LinearPosition(dims, sigma=1.0, learnable=False),
                     clutter_intensity=20 / SIDE**2, birth_weight=0.5,
                     birth_mean=torch.tensor([SIDE / 2] * dims + [0.0] * dims),
                     birth_cov=torch.diag(torch.tensor([SIDE**2] * dims + [4.0] * dims)), capacity=16,
                     lbp_tol=None, sparse=sparse, learnable=False).double()   # fixed iterations: the same in both


@pytest.mark.parametrize("seed", range(3))
def test_sparse_update_equals_the_dense_one_on_random_scenes(seed):
    g = torch.Generator().manual_seed(seed)
    f64 = {"dtype": torch.float64, "generator": g}
    dense, sparse = _filter(False), _filter(True)
    sd, ss = dense.init_state(), sparse.init_state()
    x, v = torch.rand(30, 2, **f64) * SIDE, torch.randn(30, 2, **f64)
    for _ in range(12):
        x = x + v
        seen = x[torch.rand(30, generator=g) < 0.9]
        z = torch.cat([seen + torch.randn(seen.shape, **f64), torch.rand(20, 2, **f64) * SIDE])
        z = z[torch.randperm(z.shape[0], generator=g)]
        sd, info_d = dense.step(sd, z)
        ss, info_s = sparse.step(ss, z)
        assert torch.equal(sd.label, ss.label)
        for a, b in ((sd.existence, ss.existence), (sd.mean, ss.mean), (sd.cov, ss.cov),
                     (sd.poisson_log_weight, ss.poisson_log_weight)):
            torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-10)
        md, ms = info_d.marginals, info_s.marginals
        torch.testing.assert_close(ms.assoc, md.assoc[ms.row, ms.col], rtol=0, atol=1e-10)
        torch.testing.assert_close(ms.new, md.new, rtol=0, atol=1e-10)
        assert float(md.assoc.sum()) == pytest.approx(float(ms.assoc.sum()), abs=1e-9)   # no gated pair missed
    assert int(sparse.estimate(ss).mask.sum()) >= 20                   # the scene has tracks to compare


def test_sparse_association_needs_an_unbatched_state_and_planar_measurements():
    filt = _filter(True)
    with pytest.raises(TorchtrackError, match="unbatched"):
        filt.update(filt.init_state((2,)), torch.zeros(2, 3, 2, dtype=torch.float64))
    with pytest.raises(TorchtrackError, match="2-D measurements"):
        _filter(True, dims=3)


def test_sparse_update_takes_empty_scans_and_an_empty_state():
    """No measurement, or no Bernoulli yet: the same as the dense path, no NaN; empty scans prune every track."""
    dense, sparse = _filter(False), _filter(True)
    z = torch.tensor([[50.0, 60.0], [120.0, 30.0]], dtype=torch.float64)
    sd, ss = dense.step(dense.init_state(), z), sparse.step(sparse.init_state(), z)
    sd, ss = sd[0], ss[0]
    for _ in range(60):
        sd, _ = dense.step(sd, z[:0])
        ss, _ = sparse.step(ss, z[:0])
        torch.testing.assert_close(ss.existence, sd.existence, rtol=1e-10, atol=1e-12)
        assert bool(torch.isfinite(ss.mean).all() and torch.isfinite(ss.cov).all())
    assert not bool(ss.valid.any())


def test_all_pairs_screen_equals_the_grid(monkeypatch):
    """Up to DENSE_PAIRS the gated pairs come from testing every pair; the grid gives the same pairs, in the
    same order, with the same likelihoods and innovations."""
    from torchtrack.filters.pmb import sparse as sparse_mod

    g = torch.Generator().manual_seed(5)
    f64 = {"dtype": torch.float64, "generator": g}
    N, M = 40, 60
    mean = torch.cat([torch.rand(N, 2, **f64) * SIDE, torch.randn(N, 2, **f64)], 1)
    A = torch.randn(N, 4, 4, **f64)
    cov = A @ A.transpose(-1, -2) * 4 + torch.eye(4, dtype=torch.float64)
    valid = torch.rand(N, generator=g) < 0.8
    z = torch.cat([mean[:30, :2] + torch.randn(30, 2, **f64), torch.rand(M - 30, 2, **f64) * SIDE])
    zmask = torch.rand(M, generator=g) < 0.9
    H, R = torch.eye(2, 4, dtype=torch.float64), torch.eye(2, dtype=torch.float64)
    dense = sparse_mod.gated_pairs(mean, cov, valid, z, zmask, H, R, 9.21)
    monkeypatch.setattr(sparse_mod, "DENSE_PAIRS", 0)
    grid = sparse_mod.gated_pairs(mean, cov, valid, z, zmask, H, R, 9.21)
    assert dense.row.numel() >= 30
    assert torch.equal(dense.row, grid.row) and torch.equal(dense.col, grid.col)
    for a, b in ((dense.log_lik, grid.log_lik), (dense.innovation, grid.innovation), (dense.gain, grid.gain)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_lbp_on_the_gated_lines_equals_the_whole_matrix():
    """LBP on the Bernoullis and measurements with a gated pair, the rest filled in (p_i(0) = p_j(new) = 1),
    equals LBP on the whole matrix (float64)."""
    from torchtrack.association.lbp import lbp_marginals
    from torchtrack.filters.pmb.filter import _lbp_on_gated_lines

    g = torch.Generator().manual_seed(2)
    n, m = 30, 40
    gated = torch.rand(n, m, generator=g) < 0.08
    gated[:5] = False                                            # Bernoullis and measurements without a pair
    gated[:, :6] = False
    log_w = torch.where(gated, torch.randn(n, m, generator=g, dtype=torch.float64), float("-inf"))
    log_miss = torch.randn(n, generator=g, dtype=torch.float64)
    log_new = torch.randn(m, generator=g, dtype=torch.float64)
    with torch.no_grad():
        whole = lbp_marginals(log_w, log_miss, log_new, iterations=40, tol=None, check=False)
        lines = _lbp_on_gated_lines(log_w, log_miss, log_new, gated, 40, None)
    for a, b in zip(lines[:4], whole[:4]):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert float(lines.miss[:5].min()) == 1.0 and float(lines.new[:6].min()) == 1.0
    assert float(whole.assoc.sum()) > 1.0                        # pairs took part
