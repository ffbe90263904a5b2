"""Bad input gets a clear error naming the argument; NaN measurements are masked, never propagated."""

import pytest
import torch

from torchtrack import TorchtrackError
from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter
from torchtrack.gaussian import log_prob
from torchtrack.models import ConstantVelocity, LinearMeasurement, LinearMotion, LinearPosition
from torchtrack.params import Covariance, Positive, Probability, RowStochastic


@pytest.fixture
def kf():
    return KalmanFilter(ConstantVelocity(2, q=0.1), LinearPosition(2, sigma=1.0)).double()


def _state(batch=(3,)):
    eye = torch.eye(4, dtype=torch.float64)
    return GaussianState(torch.zeros(*batch, 4, dtype=torch.float64), eye.expand(*batch, 4, 4))


def test_wrong_measurement_shape(kf):
    with pytest.raises(TorchtrackError, match="measurement z must have shape"):
        kf.update(_state(), torch.zeros(3, 3, dtype=torch.float64))


def test_wrong_state_shape(kf):
    with pytest.raises(TorchtrackError, match="state mean"):
        kf.predict(GaussianState(torch.zeros(3, 5, dtype=torch.float64), torch.eye(4, dtype=torch.float64)))


def test_non_positive_definite_state_covariance_is_named(kf):
    bad = GaussianState(torch.zeros(4, dtype=torch.float64), -torch.eye(4, dtype=torch.float64))
    with pytest.raises(TorchtrackError, match="innovation covariance S"):
        kf.update(bad, torch.zeros(2, dtype=torch.float64))


def test_log_prob_names_a_covariance_that_is_not_positive_definite():
    with pytest.raises(TorchtrackError, match="not positive definite"):
        log_prob(torch.zeros(2), torch.zeros(2), torch.zeros(2, 2))


def test_model_parameter_errors():
    with pytest.raises(TorchtrackError, match="process noise q must be > 0"):
        ConstantVelocity(2, q=-1.0)
    with pytest.raises(TorchtrackError, match="measurement noise sigma must be > 0"):
        LinearPosition(2, sigma=0.0)
    with pytest.raises(TorchtrackError, match="process noise Q must be positive definite"):
        LinearMotion(torch.eye(2), -torch.eye(2))
    with pytest.raises(TorchtrackError, match="measurement noise R must be square"):
        LinearMeasurement(torch.ones(1, 2), torch.ones(2, 3))
    with pytest.raises(TorchtrackError, match="dt must be > 0"):
        ConstantVelocity(2).transition_matrix(0.0)
    with pytest.raises(TorchtrackError, match="dt must be > 0"):
        ConstantVelocity(2).process_noise(torch.tensor([1.0, -1.0]))
    with pytest.raises(TorchtrackError, match="state size"):
        KalmanFilter(ConstantVelocity(2), LinearPosition(3))


def test_param_constraints():
    with pytest.raises(TorchtrackError, match="between 0 and 1"):
        Probability(1.0, "p_D")
    with pytest.raises(TorchtrackError, match="rows of transition matrix must sum to 1"):
        RowStochastic([[0.5, 0.6], [0.5, 0.5]])
    with pytest.raises(TorchtrackError, match="must be finite"):
        Positive(float("nan"), "rate")
    with pytest.raises(TorchtrackError, match="symmetric"):
        Covariance([[1.0, 0.2], [0.0, 1.0]])


def test_params_round_trip_their_values():
    torch.testing.assert_close(Positive(2.5)(), torch.tensor(2.5))
    torch.testing.assert_close(Probability(0.9)(), torch.tensor(0.9))
    T = torch.tensor([[0.9, 0.1], [0.2, 0.8]])
    torch.testing.assert_close(RowStochastic(T)(), T)
    C = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(Covariance(C)(), C)


def test_nan_measurements_are_masked_as_missing(kf):
    state = _state()
    z = torch.tensor([[1.0, 2.0], [float("nan"), 0.0], [3.0, 3.0]], dtype=torch.float64)
    post, info = kf.update(state, z)
    assert torch.isfinite(post.mean).all() and torch.isfinite(post.cov).all()
    torch.testing.assert_close(post.mean[1], state.mean[1])
    torch.testing.assert_close(post.cov[1], state.cov[1])
    assert info.log_likelihood[1] == 0 and info.nis[1] == 0 and not info.present[1]
    # an explicit mask does the same
    post2, _ = kf.update(state, torch.nan_to_num(z), mask=torch.tensor([True, False, True]))
    torch.testing.assert_close(post2.mean, post.mean)
