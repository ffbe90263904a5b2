"""Statistical consistency, broadcasting, gradients and maximum-likelihood fitting of the Kalman filter."""

import pytest
import torch

from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter, chi2_bounds, nees
from torchtrack.gaussian import sample
from torchtrack.models import ConstantVelocity, LinearPosition

DT = 1.0


def _simulate(kf: KalmanFilter, runs: int, T: int, gen: torch.Generator, x0_cov: torch.Tensor):
    """Draw truth and measurements from exactly the filter's model (float64)."""
    F = kf.motion.transition_matrix(DT).detach()
    Q = kf.motion.process_noise(DT).detach()
    H = kf.measurement.matrix().detach()
    R = kf.measurement.noise_cov().detach()
    x = sample(torch.zeros(runs, 4, dtype=torch.float64), x0_cov, gen)
    xs, zs = [], []
    for _ in range(T):
        x = (F @ x.unsqueeze(-1)).squeeze(-1) + sample(torch.zeros(runs, 4, dtype=torch.float64), Q, gen)
        xs.append(x)
        zs.append((H @ x.unsqueeze(-1)).squeeze(-1) + sample(torch.zeros(runs, 2, dtype=torch.float64), R, gen))
    return torch.stack(xs), torch.stack(zs)


def test_nees_and_nis_within_chi_square_bounds():
    gen = torch.Generator().manual_seed(7)
    kf = KalmanFilter(ConstantVelocity(2, q=0.2), LinearPosition(2, sigma=2.0)).double()
    runs, T = 500, 40
    P0 = torch.diag(torch.tensor([4.0, 4.0, 1.0, 1.0], dtype=torch.float64))
    truth, z = _simulate(kf, runs, T, gen, P0)
    with torch.no_grad():
        res = kf.run(z, GaussianState(torch.zeros(runs, 4, dtype=torch.float64), P0.expand(runs, 4, 4)))
        e = nees(GaussianState(res.mean, res.cov), truth)     # (T, runs)
    lo, hi = chi2_bounds(4, runs)
    inside = ((e.mean(1) > lo) & (e.mean(1) < hi)).double().mean()
    assert inside >= 0.85, f"NEES inside 95% bounds at only {inside:.2f} of the steps"
    lo, hi = chi2_bounds(4, runs * T)
    assert lo < float(e.mean()) < hi
    lo, hi = chi2_bounds(2, runs * T)
    assert lo < float(res.nis.mean()) < hi
    # a mis-specified filter (R four times too small) must fail the same test
    wrong = KalmanFilter(ConstantVelocity(2, q=0.2), LinearPosition(2, sigma=1.0)).double()
    with torch.no_grad():
        bad = wrong.run(z, GaussianState(torch.zeros(runs, 4, dtype=torch.float64), P0.expand(runs, 4, 4)))
    assert float(bad.nis.mean()) > hi


@pytest.mark.parametrize("batch", [(), (5,), (3, 4)])
def test_batch_shapes_match_a_loop(batch):
    gen = torch.Generator().manual_seed(1)
    kf = KalmanFilter(ConstantVelocity(2, q=0.5), LinearPosition(2, sigma=1.0)).double()
    T = 8
    z = torch.randn(T, *batch, 2, generator=gen, dtype=torch.float64) * 3
    m0 = torch.randn(*batch, 4, generator=gen, dtype=torch.float64)
    P0 = torch.eye(4, dtype=torch.float64) * 3
    with torch.no_grad():
        res = kf.run(z, GaussianState(m0, P0))  # the covariance broadcasts against the batch
        flat_z = z.reshape(T, -1, 2)
        flat_m = m0.reshape(-1, 4)
        for i in range(flat_m.shape[0]):
            single = kf.run(flat_z[:, i], GaussianState(flat_m[i], P0))
            torch.testing.assert_close(res.mean.reshape(T, -1, 4)[:, i], single.mean, rtol=0, atol=1e-12)
            torch.testing.assert_close(res.cov.reshape(T, -1, 4, 4)[:, i], single.cov, rtol=0, atol=1e-12)
            torch.testing.assert_close(res.log_likelihood.reshape(-1)[i], single.log_likelihood, rtol=0, atol=1e-12)


def test_gradcheck_predict_update_and_sequence_loglik():
    gen = torch.Generator().manual_seed(2)
    kf = KalmanFilter(ConstantVelocity(2, q=0.5), LinearPosition(2, sigma=1.2)).double()
    z = torch.randn(6, 2, 2, generator=gen, dtype=torch.float64)
    P0 = torch.eye(4, dtype=torch.float64) * 2

    def one_step(mean, cov_factor, zk):
        cov = cov_factor @ cov_factor.transpose(-1, -2) + 0.1 * torch.eye(4, dtype=torch.float64)
        pred = kf.predict(GaussianState(mean, cov))
        post, info = kf.update(pred, zk)
        return post.mean, post.cov, info.log_likelihood

    mean = torch.randn(2, 4, generator=gen, dtype=torch.float64, requires_grad=True)
    factor = torch.randn(2, 4, 4, generator=gen, dtype=torch.float64, requires_grad=True)
    zk = z[0].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(one_step, (mean, factor, zk))

    rq = kf.motion.q.raw.detach().clone().requires_grad_(True)
    rs = kf.measurement.sigma.raw.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: _loglik_with(kf, a, b, z, P0), (rq, rs))


def _loglik_with(kf, raw_q, raw_sigma, z, P0):
    """The sequence log-likelihood as a function of the unconstrained noise parameters."""
    params = {"motion.q.raw": raw_q, "measurement.sigma.raw": raw_sigma}
    init = GaussianState(torch.zeros(z.shape[1], 4, dtype=torch.float64), P0)
    return torch.func.functional_call(kf, params, (z, init)).log_likelihood


def test_maximum_likelihood_recovers_q_and_r_within_10_percent():
    gen = torch.Generator().manual_seed(11)
    true_q, true_sigma = 0.5, 2.0
    truth_kf = KalmanFilter(ConstantVelocity(2, q=true_q), LinearPosition(2, sigma=true_sigma)).double()
    runs, T = 100, 60
    P0 = torch.diag(torch.tensor([10.0, 10.0, 4.0, 4.0], dtype=torch.float64))
    _, z = _simulate(truth_kf, runs, T, gen, P0)
    init = GaussianState(torch.zeros(runs, 4, dtype=torch.float64), P0.expand(runs, 4, 4))

    kf = KalmanFilter(ConstantVelocity(2, q=3 * true_q), LinearPosition(2, sigma=true_sigma / 3)).double()
    opt = torch.optim.LBFGS(kf.parameters(), lr=0.5, max_iter=60, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = -kf.run(z, init).log_likelihood.sum() / (runs * T)
        loss.backward()
        return loss

    opt.step(closure)
    q_hat = float(kf.motion.q().detach())
    s_hat = float(kf.measurement.sigma().detach())
    assert abs(q_hat / true_q - 1) < 0.10, q_hat
    assert abs(s_hat**2 / true_sigma**2 - 1) < 0.10, s_hat
