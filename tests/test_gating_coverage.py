"""Gates: empirical coverage against nominal 1 − α, volumes, batched against per-track evaluation."""

import math

import pytest
import torch

from torchtrack.association.gating import (
    class_conditioned_gate,
    density_gate,
    ellipsoidal_gate,
    mixture_gate,
    mixture_log_density,
    nonlinear_gate,
    rectangular_gate,
    sample_gate,
    sample_mixture,
)
from torchtrack.errors import TorchtrackError
from torchtrack.gaussian import chi2_quantile, sample
from torchtrack.models import RangeBearing

ALPHA = 0.05
F64 = torch.float64


def _tol(n, n_ref=None):
    """Four standard errors of an estimated coverage (plus the threshold's own sampling error)."""
    v = ALPHA * (1 - ALPHA) * (1 / n + (1 / n_ref if n_ref else 0.0))
    return 4 * math.sqrt(v)


def _gaussians(T=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(T, 2, 2, generator=g, dtype=F64)
    S = A @ A.transpose(-1, -2) + 0.5 * torch.eye(2, dtype=F64)
    return torch.randn(T, 2, generator=g, dtype=F64) * 10, S, g


def _self_coverage(gate_fn, z_hat, S, g, n=20000):
    """Draw n true measurements per track and gate them against that track only."""
    z = sample(z_hat, S, g, (n,)).transpose(0, 1)        # (T, n, 2)
    gate = gate_fn(z, z_hat.unsqueeze(-2), S.unsqueeze(-3))  # track batch as leading dim, one track each
    return gate.mask.squeeze(-2).double().mean(-1), gate


def test_ellipsoidal_gate_coverage_and_volume():
    z_hat, S, g = _gaussians()
    cov, gate = _self_coverage(lambda z, m, s: ellipsoidal_gate(z, m, s, ALPHA), z_hat, S, g)
    assert (cov - (1 - ALPHA)).abs().max() < _tol(20000)
    vol = math.pi * chi2_quantile(1 - ALPHA, 2) * torch.linalg.det(S).sqrt()
    torch.testing.assert_close(gate.volume.squeeze(-1), vol)


def test_rectangular_gate_coverage_bonferroni():
    z_hat, S, g = _gaussians(seed=1)
    cov, _ = _self_coverage(lambda z, m, s: rectangular_gate(z, m, s, ALPHA), z_hat, S, g)
    assert (cov >= 1 - ALPHA - _tol(20000)).all()           # Bonferroni: at least 1 − α
    diag = torch.diag_embed(torch.diagonal(S, dim1=-2, dim2=-1))
    cov_d, gate = _self_coverage(lambda z, m, s: rectangular_gate(z, m, s, ALPHA), z_hat, diag, g)
    exact = (1 - ALPHA / 2) ** 2                              # independent axes: (1 − α/n)^n ≈ 1 − α
    assert (cov_d - exact).abs().max() < _tol(20000)
    assert abs(exact - (1 - ALPHA)) < _tol(20000)
    from scipy.stats import norm

    gam = norm.ppf(1 - ALPHA / 4)
    sd = torch.diagonal(S, dim1=-2, dim2=-1).sqrt()
    torch.testing.assert_close(gate.volume.squeeze(-1), 4 * gam**2 * sd.prod(-1))


def _bimodal(T=4, seed=2):
    g = torch.Generator().manual_seed(seed)
    log_w = torch.log(torch.tensor([[0.5, 0.5], [0.7, 0.3], [0.4, 0.6], [0.8, 0.2]], dtype=F64))[:T]
    mean = torch.stack([torch.zeros(T, 2, dtype=F64), torch.tensor([8.0, 3.0], dtype=F64).expand(T, 2)], -2)
    mean = mean + torch.randn(T, 1, 2, generator=g, dtype=F64)
    cov = torch.eye(2, dtype=F64).expand(T, 2, 2, 2) * torch.tensor([1.0, 2.0], dtype=F64)[:, None, None]
    return log_w, mean, cov.contiguous(), g


def test_sample_based_gate_coverage_on_mixture_and_volume_below_ellipse():
    log_w, mean, cov, g = _bimodal()
    N = 20000
    gate_samples = sample_mixture(log_w, mean, cov, N, g)            # (T, N, 2)
    truth = sample_mixture(log_w, mean, cov, N, g)                   # fresh true measurements
    hdr = mixture_gate(truth, log_w.unsqueeze(-2), mean.unsqueeze(-3), cov.unsqueeze(-4), ALPHA, N, g)
    cov_hdr = hdr.mask.squeeze(-2).double().mean(-1)
    assert (cov_hdr - (1 - ALPHA)).abs().max() < _tol(N, N)
    # the same through the class-conditioned gate's exact-density region
    cc = class_conditioned_gate(truth, log_w.unsqueeze(-2), mean.unsqueeze(-3), cov.unsqueeze(-4), ALPHA,
                                region="density", num_samples=N, generator=g)
    assert (cc.mask.squeeze(-2).double().mean(-1) - (1 - ALPHA)).abs().max() < _tol(N, N)
    # ellipse of the moment-matched Gaussian, calibrated to the same coverage on the mixture
    from torchtrack.gaussian import moment_match

    mu, S = moment_match(log_w, mean, cov)
    nis = ellipsoidal_gate(gate_samples, mu.unsqueeze(-2), S.unsqueeze(-3), ALPHA).distance.squeeze(-2)
    thr = torch.quantile(nis, 1 - ALPHA, dim=-1)
    ell = ellipsoidal_gate(truth, mu.unsqueeze(-2), S.unsqueeze(-3), threshold=thr.unsqueeze(-1))
    assert (ell.mask.squeeze(-2).double().mean(-1) - (1 - ALPHA)).abs().max() < _tol(N, N)
    assert (hdr.volume < ell.volume).all()
    # the importance-sampling volume agrees with the area of the region counted on a grid
    log_gamma = -hdr.threshold[0, 0]
    xs = torch.linspace(-8, 16, 481, dtype=F64)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    inside = mixture_log_density(grid, log_w[0], mean[0], cov[0]) >= log_gamma
    area = inside.double().sum() * (xs[1] - xs[0]) ** 2
    assert float(hdr.volume[0, 0]) == pytest.approx(float(area), rel=0.03)


def test_density_gate_of_a_gaussian_is_the_ellipse():
    z_hat, S, g = _gaussians(T=3, seed=4)
    N = 40000
    s = sample(z_hat, S, g, (N,)).transpose(0, 1)
    logp = mixture_log_density(s, torch.zeros(3, 1, dtype=F64), z_hat.unsqueeze(-2), S.unsqueeze(-3))
    gate = density_gate(logp.unsqueeze(-2)[..., :10], logp.unsqueeze(-2), ALPHA)
    ell = ellipsoidal_gate(s[:, :10], z_hat.unsqueeze(-2), S.unsqueeze(-3), ALPHA)
    torch.testing.assert_close(gate.volume, ell.volume, rtol=0.03, atol=0)


def test_nonlinear_range_bearing_gate_coverage():
    g = torch.Generator().manual_seed(5)
    sensor = RangeBearing((0.0, 0.0), sigma_range=5.0, sigma_bearing=0.02).double()
    mean = torch.tensor([[300.0, 400.0, 0, 0], [-200.0, 500.0, 0, 0]], dtype=F64)
    P = torch.diag(torch.tensor([400.0, 100.0, 1.0, 1.0], dtype=F64))
    x = sample(mean, P, g, (200,)).transpose(0, 1)             # (T, P, 4) predicted-state samples
    n = 4000
    pick = torch.randint(0, 200, (2, n), generator=g)
    xt = torch.gather(x, 1, pick.unsqueeze(-1).expand(2, n, 4))
    R = sensor.noise_cov()
    z = sensor.measure(xt) + sample(torch.zeros(2, dtype=F64), R, g, (2, n))
    gate = nonlinear_gate(z, x.unsqueeze(-3), sensor, ALPHA, num_samples=4000, generator=g)
    cov = gate.mask.squeeze(-2).double().mean(-1)
    assert (cov - (1 - ALPHA)).abs().max() < _tol(n, 4000)


def test_batched_masks_equal_per_track():
    g = torch.Generator().manual_seed(7)
    T, Mz = 5, 30
    z_hat, S, _ = _gaussians(T, seed=7)
    z = torch.randn(Mz, 2, generator=g, dtype=F64) * 15
    z_mask = torch.rand(Mz, generator=g) < 0.9
    log_w, mean, cov, _ = _bimodal(4, seed=8)
    mean, cov = mean.repeat(2, 1, 1)[:T] * 2, cov.repeat(2, 1, 1, 1)[:T]
    log_w = log_w.repeat(2, 1)[:T]
    samples = sample_mixture(log_w, mean, cov, 500, g)

    def dens(x):
        return mixture_log_density(x, log_w, mean, cov)

    batched = {
        "rect": rectangular_gate(z, z_hat, S, ALPHA, z_mask),
        "ell": ellipsoidal_gate(z, z_hat, S, ALPHA, z_mask),
        "cc": class_conditioned_gate(z, log_w, mean, cov, ALPHA, z_mask=z_mask),
        "sample": sample_gate(z, samples, dens, ALPHA, z_mask),
    }
    for t in range(T):
        single = {
            "rect": rectangular_gate(z, z_hat[t:t + 1], S[t:t + 1], ALPHA, z_mask),
            "ell": ellipsoidal_gate(z, z_hat[t:t + 1], S[t:t + 1], ALPHA, z_mask),
            "cc": class_conditioned_gate(z, log_w[t:t + 1], mean[t:t + 1], cov[t:t + 1], ALPHA, z_mask=z_mask),
            "sample": sample_gate(z, samples[t:t + 1],
                                  lambda x, t=t: mixture_log_density(x, log_w[t:t + 1], mean[t:t + 1], cov[t:t + 1]),
                                  ALPHA, z_mask),
        }
        for k in batched:
            assert torch.equal(batched[k].mask[t], single[k].mask[0]), k
            torch.testing.assert_close(batched[k].volume[t], single[k].volume[0])
    assert batched["ell"].mask.any() and not batched["ell"].mask.all()


@pytest.mark.parametrize("alpha", [0.0, 1.0, -0.1, 1.5])
def test_alpha_outside_unit_interval_is_an_error(alpha):
    z = torch.zeros(3, 2)
    S = torch.eye(2).expand(1, 2, 2)
    with pytest.raises(TorchtrackError, match=r"alpha .* must lie in \(0, 1\)"):
        ellipsoidal_gate(z, torch.zeros(1, 2), S, alpha)
    with pytest.raises(TorchtrackError, match=r"alpha"):
        rectangular_gate(z, torch.zeros(1, 2), S, alpha)
    with pytest.raises(TorchtrackError, match=r"alpha"):
        mixture_gate(z, torch.zeros(1, 1), torch.zeros(1, 1, 2), S.unsqueeze(1), alpha, 10)
