"""The batched Gaussian core against torch.distributions and closed forms."""

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.gaussian import (
    chi2_quantile,
    cholesky,
    gain_from_cholesky,
    kalman_gain,
    kalman_update,
    leading_gain,
    log_prob,
    mahalanobis_sq,
    moment_match,
    sample,
)


def _spd(gen, *batch, n):
    A = torch.randn(*batch, n, n, generator=gen, dtype=torch.float64)
    return A @ A.transpose(-1, -2) + n * torch.eye(n, dtype=torch.float64)


def test_log_prob_and_mahalanobis_match_torch_distributions_with_broadcasting():
    gen = torch.Generator().manual_seed(0)
    cov = _spd(gen, 4, 1, n=3)                       # (4, 1, 3, 3)
    mean = torch.randn(1, 5, 3, generator=gen, dtype=torch.float64)
    x = torch.randn(4, 5, 3, generator=gen, dtype=torch.float64)
    ref = torch.distributions.MultivariateNormal(mean, covariance_matrix=cov)
    torch.testing.assert_close(log_prob(x, mean, cov), ref.log_prob(x))
    d2 = mahalanobis_sq(x, mean, cholesky(cov))
    brute = ((x - mean).unsqueeze(-2) @ torch.linalg.solve(cov, (x - mean).unsqueeze(-1))).squeeze(-1).squeeze(-1)
    torch.testing.assert_close(d2, brute)


def test_kalman_update_matches_the_information_form():
    gen = torch.Generator().manual_seed(1)
    P = _spd(gen, 6, n=4)
    R = _spd(gen, n=2)
    H = torch.randn(2, 4, generator=gen, dtype=torch.float64)
    m = torch.randn(6, 4, generator=gen, dtype=torch.float64)
    z = torch.randn(6, 2, generator=gen, dtype=torch.float64)
    out = kalman_update(m, P, z, H, R)
    # information form: P⁺⁻¹ = P⁻¹ + Hᵀ R⁻¹ H,  P⁺⁻¹ x⁺ = P⁻¹ x + Hᵀ R⁻¹ z
    info = torch.linalg.inv(P) + H.T @ torch.linalg.inv(R) @ H
    torch.testing.assert_close(out.cov, torch.linalg.inv(info))
    rhs = (torch.linalg.inv(P) @ m.unsqueeze(-1)).squeeze(-1) + (H.T @ torch.linalg.inv(R) @ z.T).T
    torch.testing.assert_close(out.mean, torch.linalg.solve(info, rhs))
    S = H @ P @ H.T + R
    ref = torch.distributions.MultivariateNormal((H @ m.unsqueeze(-1)).squeeze(-1), S).log_prob(z)
    torch.testing.assert_close(out.log_likelihood, ref)


def test_moment_match_equals_sample_moments_of_the_mixture():
    gen = torch.Generator().manual_seed(2)
    K, n = 3, 2
    logw = torch.log(torch.tensor([0.2, 0.5, 0.3], dtype=torch.float64))
    means = torch.randn(K, n, generator=gen, dtype=torch.float64) * 3
    covs = _spd(gen, K, n=n) / 4
    mu, P = moment_match(logw, means, covs)
    N = 400_000
    comp = torch.multinomial(logw.exp(), N, replacement=True, generator=gen)
    xs = sample(means[comp], covs[comp], gen)
    torch.testing.assert_close(mu, xs.mean(0), atol=0.03, rtol=0)
    torch.testing.assert_close(P, torch.cov(xs.T), atol=0.06, rtol=0.02)
    # -inf weights are ignored
    mu2, P2 = moment_match(torch.cat([logw, torch.tensor([-float("inf")], dtype=torch.float64)]),
                           torch.cat([means, 100 + means[:1]]), torch.cat([covs, covs[:1]]))
    torch.testing.assert_close(mu2, mu)
    torch.testing.assert_close(P2, P)


def test_sampling_is_reproducible_with_a_generator():
    cov = torch.eye(2, dtype=torch.float64)
    a = sample(torch.zeros(2, dtype=torch.float64), cov, torch.Generator().manual_seed(5), (3,))
    b = sample(torch.zeros(2, dtype=torch.float64), cov, torch.Generator().manual_seed(5), (3,))
    torch.testing.assert_close(a, b)


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 6])
def test_chi2_quantile_matches_scipy(dof):
    from scipy.stats import chi2

    for p in (0.5, 0.9, 0.99, 0.999, 0.9999):
        assert chi2_quantile(p, dof) == pytest.approx(float(chi2.ppf(p, dof)), rel=1e-12)
    assert chi2_quantile(1.0, dof) == float("inf")
    with pytest.raises(TorchtrackError, match="probability"):
        chi2_quantile(0.0, dof)


@pytest.mark.parametrize("batch", [3, 200])          # the LAPACK and the unrolled small-matrix paths
@pytest.mark.parametrize("m", [1, 2, 3])
def test_kalman_gain_against_a_dense_solve(batch, m):
    g = torch.Generator().manual_seed(batch + m)
    n = 4
    A = torch.randn(batch, m, m, generator=g, dtype=torch.float64)
    S = A @ A.transpose(-1, -2) + 0.5 * torch.eye(m, dtype=torch.float64)
    C = torch.randn(batch, n, m, generator=g, dtype=torch.float64)
    gain = kalman_gain(S, C)
    K = torch.linalg.solve(S, C.transpose(-1, -2)).transpose(-1, -2)
    torch.testing.assert_close(gain.gain, K, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(gain.chol @ gain.chol.transpose(-1, -2), S, rtol=1e-12, atol=1e-12)
    W = gain.white_cross
    torch.testing.assert_close(W @ W.transpose(-1, -2), K @ S @ K.transpose(-1, -2), rtol=1e-12, atol=1e-12)
    with pytest.raises(TorchtrackError, match="innovation covariance S"):
        kalman_gain(-S, C)


@pytest.mark.parametrize("batch", [3, 200])          # the LAPACK and the unrolled small-matrix paths
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_leading_gain_is_the_gain_of_the_leading_block_to_the_bit(batch, dtype):
    g = torch.Generator().manual_seed(batch)
    S = (_spd(g, batch, n=4) * torch.rand(batch, 1, 1, generator=g, dtype=torch.float64) * 50).to(dtype)
    C = torch.randn(batch, 4, 4, generator=g, dtype=torch.float64).to(dtype)
    gain = kalman_gain(S, C)
    for p in (1, 2, 3):
        lead, alone = leading_gain(gain, C[..., :p]), gain_from_cholesky(gain.chol[..., :p, :p], C[..., :p])
        for a, b in zip(lead, alone):
            assert torch.equal(a, b), p
        K = torch.linalg.solve(S[..., :p, :p].double(), C[..., :p].double().transpose(-1, -2)).transpose(-1, -2)
        torch.testing.assert_close(lead.gain.double(), K, **({} if dtype == torch.float32 else
                                                              {"rtol": 1e-10, "atol": 1e-10}))


def test_scalar_under_torch_compile_gives_no_warning():
    """``bench kf`` compiles the filters: the cached constant must not make Dynamo warn about its cache."""
    import warnings

    from torchtrack.gaussian import scalar

    x = torch.randn(5, dtype=torch.float64)
    step = torch.compile(lambda t: t * scalar(0.5, t) + scalar(2.0, t), backend="eager", fullgraph=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = step(x)
    torch.testing.assert_close(got, x * 0.5 + 2.0, rtol=0, atol=0)
