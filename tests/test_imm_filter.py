"""IMM: against FilterPy's IMMEstimator, against the Kalman filter, fast path against general path."""

import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.imm.cv import ConstantVelocityIMM
from torchtrack.filters.imm.filter import InteractingMultipleModel
from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter
from torchtrack.models import ConstantAcceleration, ConstantVelocity, LinearPosition, ModeControlInput
from torchtrack.params import RowStochastic

DT = 1.0


def _measurements(T=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float64)
    x = 10 * t + 3 * torch.where(t > 20, (t - 20) ** 2, torch.zeros_like(t))
    y = 5 * t
    return torch.stack([x, y], -1) + 4 * torch.randn(T, 2, generator=g, dtype=torch.float64)


def test_imm_matches_filterpy_two_model_cv():
    filterpy = pytest.importorskip("filterpy.kalman")
    qs, sigma = [0.1, 30.0], 4.0
    Tm = np.array([[0.95, 0.05], [0.1, 0.9]])
    x0 = np.array([0.0, 0.0, 8.0, 4.0])
    P0 = np.diag([50.0, 50.0, 20.0, 20.0])
    filters = [KalmanFilter(ConstantVelocity(2, q, noise="pwca"), LinearPosition(2, sigma=sigma)).double()
               for q in qs]
    imm = InteractingMultipleModel(filters, torch.tensor(Tm))
    z = _measurements()
    state = imm.initial_state(torch.tensor(x0), torch.tensor(P0), torch.tensor([0.6, 0.4]))

    fps = []
    for f in filters:
        kf = filterpy.KalmanFilter(dim_x=4, dim_z=2)
        kf.F = f.motion.transition_matrix(DT).detach().numpy()
        kf.Q = f.motion.process_noise(DT).detach().numpy()
        kf.H = f.measurement.matrix().detach().numpy()
        kf.R = f.measurement.noise_cov().detach().numpy()
        kf.x = x0.reshape(4, 1).copy()
        kf.P = P0.copy()
        fps.append(kf)
    ref = filterpy.IMMEstimator(fps, np.array([0.6, 0.4]), Tm)
    for k in range(z.shape[0]):
        state = imm.predict(state, DT)
        state, _ = imm.update(state, z[k])
        ref.predict()
        ref.update(z[k].numpy().reshape(2, 1))
        est = imm.combine(state)
        np.testing.assert_allclose(state.log_prob.exp().detach().numpy(), ref.mu, atol=1e-6)
        np.testing.assert_allclose(est.mean.detach().numpy(), ref.x.ravel(), atol=1e-6, rtol=1e-9)
        np.testing.assert_allclose(est.cov.detach().numpy(), ref.P, atol=1e-6, rtol=1e-9)


def test_single_model_imm_equals_kalman_filter():
    kf = KalmanFilter(ConstantVelocity(2, 2.0), LinearPosition(2, sigma=3.0)).double()
    imm = InteractingMultipleModel([kf], torch.ones(1, 1, dtype=torch.float64))
    z = _measurements(25).unsqueeze(1).repeat(1, 3, 1)
    z[5, 1] = float("nan")  # a missing measurement in one track
    init = GaussianState(torch.zeros(3, 4, dtype=torch.float64), 100 * torch.eye(4, dtype=torch.float64))
    out = imm.run(z, imm.initial_state(init.mean, init.cov), DT)
    # exactly the Kalman filter's own predict/update steps
    state, total = init, 0.0
    for k in range(z.shape[0]):
        state, info = kf.update(kf.predict(state, DT), z[k])
        total = total + info.log_likelihood
        assert torch.equal(out.mean[k], state.mean) and torch.equal(out.cov[k], state.cov)
    assert torch.equal(out.log_likelihood, total)
    assert torch.equal(out.mode_prob, torch.ones_like(out.mode_prob))
    # and its sequence runner (which may take a differently ordered fast path) to round-off
    ref = kf.run(z, init, DT)
    torch.testing.assert_close(out.mean, ref.mean, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(out.cov, ref.cov, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=1e-12, atol=1e-9)


def _paper_models():
    g = 9.81
    motion = ModeControlInput([[0.0, 0.0], [0.0, 3 * g], [0.0, -g]], [0.2, 0.2, 0.2]).double()
    meas = LinearPosition(2, sigma=10.0).double()
    Tm = torch.tensor([[0.95, 0.05, 0.0], [0.1, 0.8, 0.1], [0.0, 0.05, 0.95]], dtype=torch.float64)
    return motion, meas, Tm


def test_fast_cv_path_equals_general_path():
    motion, meas, Tm = _paper_models()
    fast = ConstantVelocityIMM(motion, meas, Tm)
    general = InteractingMultipleModel.from_mode_control(motion, meas, Tm)
    g = torch.Generator().manual_seed(3)
    z = _measurements(30).unsqueeze(1) + 20 * torch.randn(30, 5, 2, generator=g, dtype=torch.float64)
    z[7, 2] = float("nan")
    init = general.initial_state(torch.tensor([0.0, 0.0, 10.0, 5.0], dtype=torch.float64).expand(5, 4),
                                 torch.diag(torch.tensor([400.0, 400.0, 100.0, 100.0], dtype=torch.float64)))
    a = general.run(z, init, DT)
    b = fast.run(z, init, DT)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-8)
    # the packed loop (no missing data) agrees as well
    z2 = torch.nan_to_num(z, nan=0.0)
    ref = general.run(z2, init, DT)
    _, means, total = fast.run_packed(z2, init, DT)
    torch.testing.assert_close(means, ref.mean, rtol=1e-9, atol=1e-8)
    torch.testing.assert_close(total, ref.log_likelihood, rtol=1e-9, atol=1e-8)


def test_imm_log_likelihood_differentiable_in_noise_and_transition():
    motion = ModeControlInput([[0.0, 0.0], [0.0, 5.0]], [0.5, 2.0]).double()
    meas = LinearPosition(2, sigma=5.0).double()
    T = RowStochastic(torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=torch.float64))
    z = _measurements(15)
    init_mean = torch.tensor([0.0, 0.0, 10.0, 5.0], dtype=torch.float64)
    init_cov = 100 * torch.eye(4, dtype=torch.float64)
    for imm in (InteractingMultipleModel.from_mode_control(motion, meas, T), ConstantVelocityIMM(motion, meas, T)):
        for p in (motion.sigma.raw, meas.sigma.raw, T.raw):
            p.grad = None
        out = imm.run(z, imm.initial_state(init_mean, init_cov), DT)
        out.log_likelihood.backward()
        for p in (motion.sigma.raw, meas.sigma.raw, T.raw):
            assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    # finite-difference check of d loglik / d raw transition on the general path
    imm = InteractingMultipleModel.from_mode_control(motion, meas, T)

    def ll():
        return imm.run(z, imm.initial_state(init_mean, init_cov), DT).log_likelihood

    T.raw.grad = None
    ll().backward()
    eps = 1e-6
    with torch.no_grad():
        T.raw[0, 1] += eps
        up = ll()
        T.raw[0, 1] -= 2 * eps
        down = ll()
        T.raw[0, 1] += eps
    assert float(T.raw.grad[0, 1]) == pytest.approx(float((up - down) / (2 * eps)), rel=1e-4, abs=1e-6)


def test_imm_bad_input():
    kf = KalmanFilter(ConstantVelocity(2, 1.0), LinearPosition(2))
    with pytest.raises(TorchtrackError, match="rows of mode transition matrix must sum to 1"):
        InteractingMultipleModel([kf, kf], torch.tensor([[0.9, 0.2], [0.1, 0.9]]))
    with pytest.raises(TorchtrackError, match="shape"):
        InteractingMultipleModel([kf, kf], torch.eye(3))
    ca = KalmanFilter(ConstantAcceleration(2, 1.0), LinearPosition(2, state_dim=6))
    with pytest.raises(TorchtrackError, match="mismatched model state sizes"):
        InteractingMultipleModel([kf, ca], torch.eye(2))
    imm = InteractingMultipleModel([kf, kf], torch.eye(2))
    with pytest.raises(TorchtrackError, match="mode probabilities must sum to 1"):
        imm.initial_state(torch.zeros(4), torch.eye(4), torch.tensor([0.5, 0.6]))


def test_compiled_step_falls_back_to_eager(monkeypatch):
    import torchtrack.filters.imm.cv as imm_cv

    def broken(fn, **kw):
        def call(*args):
            raise RuntimeError("no compiler here")
        return call

    monkeypatch.setattr(imm_cv.compiled_step, "compiled", None)
    monkeypatch.setattr(imm_cv.compiled_step, "failed", False)
    monkeypatch.setattr(torch, "compile", broken)
    motion, meas, Tm = _paper_models()
    fast = ConstantVelocityIMM(motion, meas, Tm)
    z = _measurements(6).unsqueeze(1).repeat(1, 2, 1)
    init = fast.initial_state(torch.tensor([0.0, 0.0, 10.0, 5.0], dtype=torch.float64).expand(2, 4),
                              100 * torch.eye(4, dtype=torch.float64))
    with pytest.warns(UserWarning, match="running eager"):
        _, means, total = fast.run_packed(z, init, DT, compile=True)
    _, ref_means, ref_total = fast.run_packed(z, init, DT, compile=False)
    assert torch.equal(means, ref_means) and torch.equal(total, ref_total)
