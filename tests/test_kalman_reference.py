"""The Kalman-family filters against independent references (FilterPy, a NumPy textbook filter)."""

import numpy as np
import pytest
import torch

from torchtrack.filters.kalman.filter import (
    ExtendedKalmanFilter,
    GaussianState,
    KalmanFilter,
    UnscentedKalmanFilter,
)
from torchtrack.models import (
    ConstantVelocity,
    CoordinatedTurnRate,
    LinearMeasurement,
    LinearMotion,
    LinearPosition,
    RangeBearing,
)

filterpy = pytest.importorskip("filterpy.kalman")


def _random_model(rng: np.random.Generator, n: int, m: int):
    F = np.eye(n) + 0.3 * rng.standard_normal((n, n))
    A = rng.standard_normal((n, n))
    Q = A @ A.T / n + 0.1 * np.eye(n)
    H = rng.standard_normal((m, n))
    B = rng.standard_normal((m, m))
    R = B @ B.T / m + 0.5 * np.eye(m)
    return F, Q, H, R


@pytest.mark.parametrize("n,m,seed", [(2, 1, 0), (4, 2, 1), (5, 3, 2)])
def test_kalman_matches_filterpy_on_random_models(n, m, seed):
    rng = np.random.default_rng(seed)
    F, Q, H, R = _random_model(rng, n, m)
    T = 15
    z = rng.standard_normal((T, m)) * 3
    x0, P0 = rng.standard_normal(n), np.eye(n) * 4.0

    ref = filterpy.KalmanFilter(dim_x=n, dim_z=m)
    ref.x, ref.P, ref.F, ref.Q, ref.H, ref.R = x0.copy(), P0.copy(), F, Q, H, R
    ref_means, ref_covs, ref_ll = [], [], 0.0
    for k in range(T):
        ref.predict()
        ref.update(z[k])
        ref_means.append(ref.x.copy())
        ref_covs.append(ref.P.copy())
        ref_ll += ref.log_likelihood

    kf = KalmanFilter(LinearMotion(torch.tensor(F), torch.tensor(Q)),
                      LinearMeasurement(torch.tensor(H), torch.tensor(R)))
    res = kf.run(torch.tensor(z), GaussianState(torch.tensor(x0), torch.tensor(P0)))
    np.testing.assert_allclose(res.mean.detach().numpy(), np.array(ref_means), rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.cov.detach().numpy(), np.array(ref_covs), rtol=0, atol=1e-9)
    assert abs(float(res.log_likelihood.detach()) - ref_ll) < 1e-9


def _cv_problem(batch=(3,), T=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(T, *batch, 2, generator=g, dtype=torch.float64) * 2 + torch.arange(T)[:, None].expand(
        T, 2).reshape(T, *([1] * len(batch)), 2)
    init = GaussianState(torch.zeros(*batch, 4, dtype=torch.float64),
                         torch.diag(torch.tensor([5.0, 5.0, 20.0, 20.0], dtype=torch.float64)).expand(*batch, 4, 4))
    kf = KalmanFilter(ConstantVelocity(2, q=0.3), LinearPosition(2, sigma=1.5)).double()
    return kf, z, init


def test_ekf_and_ukf_equal_kf_on_linear_models():
    kf, z, init = _cv_problem()
    ekf = ExtendedKalmanFilter(kf.motion, kf.measurement)
    ukf = UnscentedKalmanFilter(kf.motion, kf.measurement, alpha=1.0, beta=0.0, kappa=0.5)
    ref = kf.run(z, init)
    for other in (ekf, ukf):
        res = other.run(z, init)
        torch.testing.assert_close(res.mean, ref.mean, rtol=0, atol=1e-9)
        torch.testing.assert_close(res.cov, ref.cov, rtol=0, atol=1e-9)
        torch.testing.assert_close(res.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-9)


def _numpy_ekf(z, x0, P0, motion, meas, dt):
    """A textbook NumPy EKF with finite-difference Jacobians (independent of torch autograd)."""
    def f(x):
        return motion.transition(torch.tensor(x)[None], dt)[0].detach().numpy()

    def h(x):
        return meas.measure(torch.tensor(x)[None])[0].detach().numpy()

    def jac(fn, x, eps=1e-6):
        cols = [(fn(x + eps * e) - fn(x - eps * e)) / (2 * eps) for e in np.eye(len(x))]
        return np.stack(cols, -1)

    Q = motion.process_noise(dt).detach().numpy()
    R = meas.noise_cov().detach().numpy()
    x, P, out = x0.copy(), P0.copy(), []
    for zk in z:
        Fj = jac(f, x)
        x = f(x)
        P = Fj @ P @ Fj.T + Q
        Hj = jac(h, x)
        S = Hj @ P @ Hj.T + R
        K = np.linalg.solve(S, Hj @ P).T
        nu = zk - h(x)
        nu[1] = (nu[1] + np.pi) % (2 * np.pi) - np.pi
        x = x + K @ nu
        P = (np.eye(len(x)) - K @ Hj) @ P
        out.append(x.copy())
    return np.array(out)


def test_ekf_nonlinear_matches_numpy_reference():
    torch.set_default_dtype(torch.float64)
    try:
        motion = CoordinatedTurnRate(sigma_a=0.5, sigma_omega=0.01)
        meas = RangeBearing((0.0, 0.0), sigma_range=5.0, sigma_bearing=0.01, state_dim=5)
    finally:
        torch.set_default_dtype(torch.float32)
    g = torch.Generator().manual_seed(3)
    T = 10
    x0 = np.array([1000.0, 2000.0, 10.0, -5.0, 0.05])
    truth = [torch.tensor(x0)]
    for _ in range(T):
        truth.append(motion.transition(truth[-1][None], 1.0)[0].detach())
    z = torch.stack([meas.measure(x[None])[0] for x in truth[1:]]).detach()
    z = z + torch.randn(z.shape, generator=g, dtype=z.dtype) * torch.tensor([5.0, 0.01])
    P0 = np.diag([100.0, 100.0, 10.0, 10.0, 0.01])
    ekf = ExtendedKalmanFilter(motion, meas)
    res = ekf.run(z, GaussianState(torch.tensor(x0), torch.tensor(P0)))
    ref = _numpy_ekf(z.numpy(), x0, P0, motion, meas, 1.0)
    np.testing.assert_allclose(res.mean.detach().numpy(), ref, rtol=1e-5, atol=1e-5)
