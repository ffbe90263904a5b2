"""The engines of :meth:`KalmanFilter.run` (batch, lanes, axes) agree with each other, with and without
history, missing measurements and a first step without prediction; the batch engine is checked against
FilterPy in ``test_kalman_reference.py``."""

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter
from torchtrack.models import ConstantVelocity, LinearPosition


def _cv_problem(batch=(3,), T=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(T, *batch, 2, generator=g, dtype=torch.float64) * 2 + torch.arange(T)[:, None].expand(
        T, 2).reshape(T, *([1] * len(batch)), 2)
    init = GaussianState(torch.zeros(*batch, 4, dtype=torch.float64),
                         torch.diag(torch.tensor([5.0, 5.0, 20.0, 20.0], dtype=torch.float64)).expand(*batch, 4, 4))
    kf = KalmanFilter(ConstantVelocity(2, q=0.3), LinearPosition(2, sigma=1.5)).double()
    return kf, z, init


def test_engines_equal_the_batch_engine_including_missing_measurements():
    kf, z, init = _cv_problem(batch=(4, 3), T=20)
    z = z.clone()
    z[5, 1, 2] = float("nan")
    z[6:9, 0, 0] = float("nan")
    ref = kf.run(z, init, engine="batch")
    for engine in ("lanes", "axes"):
        for predict_first in (True, False):
            fast = kf.run(z, init, engine=engine, predict_first=predict_first)
            ref = kf.run(z, init, engine="batch", predict_first=predict_first)
            torch.testing.assert_close(fast.mean, ref.mean, rtol=0, atol=1e-10)
            torch.testing.assert_close(fast.cov, ref.cov, rtol=0, atol=1e-10)
            torch.testing.assert_close(fast.nis, ref.nis, rtol=0, atol=1e-10)
            torch.testing.assert_close(fast.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-9)
            last = kf.run(z, init, engine=engine, predict_first=predict_first, history=False)
            torch.testing.assert_close(last.mean, ref.mean[-1:], rtol=0, atol=1e-10)
            torch.testing.assert_close(last.cov, ref.cov[-1:], rtol=0, atol=1e-10)
            torch.testing.assert_close(last.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-9)


def test_engine_choice_is_checked():
    kf, z, init = _cv_problem(batch=(3,), T=4)
    with pytest.raises(TorchtrackError, match="engine must be"):
        kf.run(z, init, engine="fast")
    bad = GaussianState(init.mean, init.cov + 0.1 * torch.ones(4, 4, dtype=init.cov.dtype))
    with pytest.raises(TorchtrackError, match="cross-axis"):
        kf.run(z, bad, engine="axes")


def test_axes_engine_takes_a_mask():
    kf, z, init = _cv_problem(batch=(5,), T=8)
    mask = torch.rand(8, 5, generator=torch.Generator().manual_seed(1)) > 0.3
    ref = kf.run(z, init, engine="batch", mask=mask)
    got = kf.run(z, init, engine="axes", mask=mask)
    torch.testing.assert_close(got.mean, ref.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(got.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-9)
