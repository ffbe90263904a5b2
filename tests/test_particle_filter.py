"""Bootstrap particle filter against the exact Kalman filter on a linear-Gaussian model."""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.particle.filter import (
    ParticleFilter,
    ParticleState,
    effective_sample_size,
    normalize,
    weighted_moments,
)
from torchtrack.gaussian import kalman_update
from torchtrack.models import ConstantVelocity, LinearPosition

DT = 1.0


def _models(q=0.5, sigma=1.0):
    return ConstantVelocity(ndim=1, q=q).double(), LinearPosition(ndim=1, sigma=sigma).double()


def _simulate(T: int, seed: int = 0):
    """Measurements of a 1-D constant-velocity target (q = 1, σ = 1), prior N(0, diag(4, 1))."""
    g = torch.Generator().manual_seed(seed)
    x = torch.tensor([0.0, 1.0], dtype=torch.float64)
    zs = []
    for _ in range(T):
        x = torch.tensor([[1.0, DT], [0.0, 1.0]], dtype=torch.float64) @ x + \
            torch.randn(2, generator=g, dtype=torch.float64) * torch.tensor([0.6, 1.0], dtype=torch.float64)
        zs.append(x[:1] + torch.randn(1, generator=g, dtype=torch.float64))
    return torch.stack(zs)


def _kalman(motion, meas, z_seq, mean, cov):
    """Exact filtering means, covariances and log-likelihood (the reference)."""
    F, Q = motion.transition_matrix(DT), motion.process_noise(DT)
    H, R = meas.matrix(), meas.noise_cov()
    means, covs, ll = [], [], 0.0
    for z in z_seq:
        mean = (F @ mean.unsqueeze(-1)).squeeze(-1)
        cov = F @ cov @ F.transpose(-1, -2) + Q
        up = kalman_update(mean, cov, z, H, R)
        mean, cov, ll = up.mean, up.cov, ll + up.log_likelihood
        means.append(mean)
        covs.append(cov)
    return torch.stack(means), torch.stack(covs), ll


PRIOR_MEAN = torch.tensor([0.0, 1.0], dtype=torch.float64)
PRIOR_COV = torch.diag(torch.tensor([4.0, 1.0], dtype=torch.float64))


@pytest.mark.parametrize("resampler", ["systematic", "multinomial"])
def test_mean_matches_kalman_within_monte_carlo_error(resampler):
    motion, meas = _models()
    z = _simulate(12)
    kf_mean, kf_cov, _ = _kalman(motion, meas, z, PRIOR_MEAN, PRIOR_COV)
    runs, n = 40, 2000
    pf = ParticleFilter(motion, meas, n, resampler=resampler)
    out = pf.run(z.unsqueeze(1).expand(-1, runs, -1), PRIOR_MEAN.expand(runs, 2), PRIOR_COV, DT,
                 torch.Generator().manual_seed(1))
    # error of each run's estimate in units of the Monte Carlo standard error sqrt(P / N)
    std = torch.diagonal(kf_cov, dim1=-2, dim2=-1).sqrt().unsqueeze(1) / math.sqrt(n)
    zscore = (out.mean - kf_mean.unsqueeze(1)) / std
    assert zscore.pow(2).mean().sqrt() < 3.0          # SIR inefficiency factor well below 9
    assert (zscore.mean(1).abs() < 4.0 * zscore.std(1) / math.sqrt(runs) + 0.3).all()   # no bias
    rel_var = torch.diagonal(out.cov, dim1=-2, dim2=-1).mean(1) / torch.diagonal(kf_cov, dim1=-2, dim2=-1)
    assert ((rel_var - 1).abs() < 0.1).all()


def test_likelihood_estimate_is_unbiased():
    motion, meas = _models()
    z = _simulate(6, seed=3)
    _, _, exact = _kalman(motion, meas, z, PRIOR_MEAN, PRIOR_COV)
    runs = 4000
    pf = ParticleFilter(motion, meas, 50, ess_threshold=None)
    out = pf.run(z.unsqueeze(1).expand(-1, runs, -1), PRIOR_MEAN.expand(runs, 2), PRIOR_COV, DT,
                 torch.Generator().manual_seed(2))
    ratio = torch.exp(out.log_likelihood - exact)
    se = ratio.std() / math.sqrt(runs)
    assert abs(ratio.mean().item() - 1.0) < 4 * se.item()
    assert se < 0.05                                  # the check has power
    assert out.log_likelihood.mean() < exact          # Jensen: log of an unbiased estimate is biased low


def test_gradient_matches_kalman_filter():
    """∂ log p̂ / ∂(q, σ) with the stop-gradient correction vs the exact Kalman gradient."""
    z = _simulate(10, seed=5)
    q0, s0 = 0.4, 1.6                                 # away from the truth: gradients are not ~0
    motion, meas = _models(q0, s0)
    _, _, exact = _kalman(motion, meas, z, PRIOR_MEAN, PRIOR_COV)
    g_exact = torch.autograd.grad(exact, [motion.q.raw, meas.sigma.raw])
    reps, n = 8, 10_000
    # one parameter copy per repeat: one backward pass yields every repeat's own gradient
    motion_b, meas_b = _models(torch.full((reps, 1, 1), q0), torch.full((reps, 1), s0))
    pf = ParticleFilter(motion_b, meas_b, n, ess_threshold=None)
    out = pf.run(z.unsqueeze(1).expand(-1, reps, -1), PRIOR_MEAN.expand(reps, 2), PRIOR_COV, DT,
                 torch.Generator().manual_seed(4))
    g_pf = torch.autograd.grad(out.log_likelihood.sum(), [motion_b.q.raw, meas_b.sigma.raw])
    for exact_g, pf_g in zip(g_exact, g_pf):
        assert abs(exact_g.item()) > 0.5
        median = pf_g.flatten().median()
        assert abs(median / exact_g - 1) < 0.2, (median, exact_g)


def test_soft_resampling_runs_and_differentiates():
    motion, meas = _models()
    z = _simulate(5)
    pf = ParticleFilter(motion, meas, 500, soft_alpha=0.5, ess_threshold=None)
    out = pf.run(z.unsqueeze(1), PRIOR_MEAN.expand(1, 2), PRIOR_COV, DT, torch.Generator().manual_seed(0))
    _, _, exact = _kalman(motion, meas, z, PRIOR_MEAN, PRIOR_COV)
    assert abs(out.log_likelihood.item() - exact.item()) < 1.0
    (g,) = torch.autograd.grad(out.log_likelihood.sum(), [meas.sigma.raw])
    assert torch.isfinite(g)


def test_jitter_rejuvenates_duplicates_with_the_kernel_spread():
    """After resampling, jitter h moves every copy by h·chol(Σ̂)·ε: no duplicates are left and the
    spread added is h² Σ̂ (Musso et al. 2001)."""
    motion, meas = _models()
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1, 4000, 2, generator=g, dtype=torch.float64) * torch.tensor([2.0, 0.5], dtype=torch.float64)
    log_w = torch.log_softmax(-0.5 * x[..., 0] ** 2, -1)          # uneven weights: many duplicates
    state = ParticleState(x, log_w, torch.zeros(1, dtype=torch.float64))
    plain = ParticleFilter(motion, meas, 4000).resample(state, torch.Generator().manual_seed(1))
    jit = ParticleFilter(motion, meas, 4000, jitter=0.3).resample(state, torch.Generator().manual_seed(1))
    assert plain.particles[0, :, 0].unique().numel() < 3000
    assert jit.particles[0, :, 0].unique().numel() == 4000
    _, cov = weighted_moments(x, log_w)
    added = (jit.particles - plain.particles)[0]
    assert torch.allclose(added.T @ added / 4000, 0.09 * cov[0], rtol=0.1, atol=1e-3)


@pytest.mark.parametrize("n", [0, -3, 2.5])
def test_bad_particle_counts_raise(n):
    motion, meas = _models()
    with pytest.raises(TorchtrackError, match="num_particles"):
        ParticleFilter(motion, meas, n)


def test_degenerate_weights_recover_without_nan():
    """All −inf weights: documented recovery — uniform weights, log-likelihood −inf, finite estimates."""
    log_w = torch.tensor([[-math.inf] * 4, [0.0, -1.0, -2.0, -math.inf]], dtype=torch.float64)
    w, ll = normalize(log_w, torch.zeros(2, dtype=torch.float64))
    assert torch.isfinite(w[0]).all() and torch.allclose(w[0].exp(), torch.full((4,), 0.25, dtype=torch.float64))
    assert ll[0] == -math.inf and torch.isfinite(ll[1])
    assert torch.allclose(effective_sample_size(log_w)[0], torch.tensor(4.0, dtype=torch.float64))
    # a measurement no particle can explain (infinite range): estimates stay finite
    motion, meas = _models()
    pf = ParticleFilter(motion, meas, 100)
    z = torch.tensor([[[math.inf]]], dtype=torch.float64)
    out = pf.run(z, PRIOR_MEAN.expand(1, 2), PRIOR_COV, DT, torch.Generator().manual_seed(0))
    assert torch.isfinite(out.mean).all() and out.log_likelihood.item() == -math.inf
