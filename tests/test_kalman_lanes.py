"""The batch-last ("lanes") Kalman filter path of ``KalmanFilter.run`` against the batch-first
predict/update loop, for a general (non-CV, 5-state, 3-measurement) linear model; the entry-by-entry
step that ``torch.compile`` fuses against the GEMM step; failures are named, never NaN."""

import pytest
import torch

from torchtrack import TorchtrackError
from torchtrack.filters.kalman import lanes
from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter, _GaussianFilter
from torchtrack.models import ConstantVelocity, LinearMeasurement, LinearMotion, LinearPosition

F64 = torch.float64


def _random_model(gen: torch.Generator, n: int = 5, m: int = 3) -> KalmanFilter:
    F = torch.eye(n, dtype=F64) + 0.3 * torch.randn(n, n, generator=gen, dtype=F64)
    A = torch.randn(n, n, generator=gen, dtype=F64)
    H = torch.randn(m, n, generator=gen, dtype=F64)
    B = torch.randn(m, m, generator=gen, dtype=F64)
    return KalmanFilter(LinearMotion(F, 0.1 * A @ A.T + 0.05 * torch.eye(n, dtype=F64)),
                        LinearMeasurement(H, B @ B.T + 0.5 * torch.eye(m, dtype=F64)))


def _sequence(gen, T, batch, m, missing=True):
    z = torch.randn(T, *batch, m, generator=gen, dtype=F64) * 3
    if missing:
        z[1, ..., 0] = float("nan")                                  # a whole step partly missing
        z.view(T, -1, m)[3, ::2] = float("nan")                      # every other track at step 3
    return z


@pytest.mark.parametrize("predict_first", [True, False])
@pytest.mark.parametrize("batch", [(), (7,), (2, 3)])
def test_lanes_run_matches_the_batch_first_loop(batch, predict_first):
    gen = torch.Generator().manual_seed(3)
    kf = _random_model(gen)
    T, n = 6, kf.state_dim
    z = _sequence(gen, T, batch, kf.measurement.meas_dim)
    mask = torch.rand(T, *batch, generator=gen) > 0.2
    A = torch.randn(n, n, generator=gen, dtype=F64)
    init = GaussianState(torch.randn(*batch, n, generator=gen, dtype=F64), A @ A.T + torch.eye(n, dtype=F64))
    with torch.no_grad():
        got = kf.run(z, init, mask=mask, predict_first=predict_first)
        ref = _GaussianFilter.run(kf, z, init, mask=mask, predict_first=predict_first)
    for name in ("mean", "cov", "nis", "log_likelihood"):
        torch.testing.assert_close(getattr(got, name), getattr(ref, name), rtol=1e-10, atol=1e-10)
    assert got.cov.shape == (T, *batch, n, n) and torch.isfinite(got.cov).all()


@pytest.mark.parametrize("model", ["random", "cv"])
@pytest.mark.parametrize("predict_first", [True, False])
def test_entrywise_step_equals_the_gemm_step(predict_first, model):
    gen = torch.Generator().manual_seed(4)
    kf = (_random_model(gen) if model == "random"
          else KalmanFilter(ConstantVelocity(2, q=0.3), LinearPosition(2, sigma=0.7)).double())
    n, m, B = kf.state_dim, kf.measurement.meas_dim, 11
    mats = kf._shared_matrices(0.5)
    patterns = (None, tuple(lanes.structure(M) for M in mats))
    if model == "cv":   # structural zeros and ones are found (and then skipped)
        assert patterns[1][0] == ((1, 0, 2, 0), (0, 1, 0, 2), (0, 0, 1, 0), (0, 0, 0, 1))
    A = torch.randn(B, n, n, generator=gen, dtype=F64)
    x = torch.randn(n, B, generator=gen, dtype=F64)
    P = (A @ A.transpose(-1, -2) + torch.eye(n, dtype=F64)).permute(1, 2, 0).contiguous()
    z = torch.randn(m, B, generator=gen, dtype=F64)
    present = torch.rand(B, generator=gen) > 0.3
    with torch.no_grad():
        for pres, pattern in [(p, q) for p in (None, present) for q in patterns]:
            want = lanes.step(x, P, z, pres, *mats, predict_first)
            out = (torch.empty_like(x), torch.empty_like(P), torch.empty(B, dtype=F64), torch.ones(B, dtype=F64),
                   torch.empty(B, dtype=torch.bool))
            lanes.fused_step(x, P, z, pres, *mats, *out, predict_first, pattern)
            got = (out[0], out[1], out[2], out[3] - 1, out[4])
            for g, w in zip(got, want):
                torch.testing.assert_close(g, w, rtol=1e-10, atol=1e-10)


def test_compiled_run_plumbing_matches_eager(monkeypatch):
    """``run(compile=True)`` through the history-writing loop (the compiled function swapped for the
    same Python function run eagerly, so the test does not pay for compilation)."""
    monkeypatch.setattr(lanes, "compiled_step", lanes.fused_step)
    gen = torch.Generator().manual_seed(5)
    kf = _random_model(gen)
    z = _sequence(gen, 5, (4,), kf.measurement.meas_dim)
    init = GaussianState(torch.zeros(4, kf.state_dim, dtype=F64), 2 * torch.eye(kf.state_dim, dtype=F64))
    with torch.no_grad():
        for predict_first in (True, False):
            got = kf.run(z, init, predict_first=predict_first, compile=True)
            ref = kf.run(z, init, predict_first=predict_first)
            for name in ("mean", "cov", "nis", "log_likelihood"):
                torch.testing.assert_close(getattr(got, name), getattr(ref, name), rtol=1e-10, atol=1e-10)


def test_failed_factorisation_names_filter_and_step():
    kf = KalmanFilter(ConstantVelocity(2, q=0.1), LinearPosition(2, sigma=1.0)).double()
    z = torch.zeros(4, 3, 2, dtype=F64)
    cov = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    cov[1] = -5 * torch.eye(4, dtype=F64)                             # one bad track
    with pytest.raises(TorchtrackError, match=r"Kalman filter: innovation covariance S .* at step 0 \(1 of 3"):
        kf.run(z, GaussianState(torch.zeros(3, 4, dtype=F64), cov), predict_first=False)


def test_missing_measurements_never_propagate_nan():
    gen = torch.Generator().manual_seed(6)
    kf = KalmanFilter(ConstantVelocity(2, q=0.1), LinearPosition(2, sigma=1.0)).double()
    z = torch.randn(5, 8, 2, generator=gen, dtype=F64)
    z[2, 3] = float("nan")
    init = GaussianState(torch.zeros(8, 4, dtype=F64), 4 * torch.eye(4, dtype=F64))
    res = kf.run(z, init)
    assert torch.isfinite(res.mean).all() and torch.isfinite(res.log_likelihood).all()
    assert res.nis[2, 3] == 0
    masked = kf.run(torch.nan_to_num(z), init, mask=~torch.isnan(z).any(-1))
    torch.testing.assert_close(masked.mean, res.mean)
    # gradients flow through the present tracks and stay finite
    kf.zero_grad()
    kf.run(z, init).log_likelihood.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in kf.parameters())


def test_lanes_update_matches_the_batch_first_update_with_broadcasting():
    gen = torch.Generator().manual_seed(8)
    kf = _random_model(gen)
    n, m = kf.state_dim, kf.measurement.meas_dim
    A = torch.randn(n, n, generator=gen, dtype=F64)
    state = GaussianState(torch.randn(n, generator=gen, dtype=F64), A @ A.T + torch.eye(n, dtype=F64))  # batch ()
    z = torch.randn(4, 5, m, generator=gen, dtype=F64)                                                  # (4, 5)
    z[0, 1, 2] = float("nan")
    mask = torch.rand(4, 5, generator=gen) > 0.3
    post, info = kf.update(state, z, mask)
    ref_post, ref_info = _GaussianFilter.update(kf, state, z, mask)
    for got, want in zip((*post, *info), (*ref_post, *ref_info)):
        torch.testing.assert_close(got, want.expand_as(got), rtol=1e-10, atol=1e-10)
    assert post.cov.shape == (4, 5, n, n)


def test_compile_failure_falls_back_to_eager(monkeypatch):
    def broken(fn, **kw):
        def call(*args):
            raise RuntimeError("no compiler here")
        return call

    monkeypatch.setattr(torch, "compile", broken)
    monkeypatch.setattr(lanes.compiled_step, "compiled", None)
    monkeypatch.setattr(lanes.compiled_step, "failed", False)
    kf = KalmanFilter(ConstantVelocity(2, q=0.1), LinearPosition(2, sigma=1.0)).double()
    z = torch.randn(4, 3, 2, generator=torch.Generator().manual_seed(9), dtype=F64)
    init = GaussianState(torch.zeros(3, 4, dtype=F64), torch.eye(4, dtype=F64))
    with torch.no_grad():
        with pytest.warns(UserWarning, match="running eagerly"):
            got = kf.run(z, init, compile=True)
        ref = kf.run(z, init)
    for name in ("mean", "cov", "nis", "log_likelihood"):
        torch.testing.assert_close(getattr(got, name), getattr(ref, name), rtol=1e-12, atol=1e-12)
