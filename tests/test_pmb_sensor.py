"""Uncertain sensor state: joint vehicle–feature update vs the exact joint Kalman update, inflation, errors."""

from __future__ import annotations

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb.filter import PMBFilter
from torchtrack.filters.pmb.sensor import JointSensorPMB, SensorState, v2f_update
from torchtrack.gaussian import kalman_update
from torchtrack.models import ConstantVelocity, LinearPosition

F64 = torch.float64


def make(p_detection: float = 0.9, clutter: float = 1e-5) -> tuple[PMBFilter, JointSensorPMB]:
    filt = PMBFilter(ConstantVelocity(2, q=0.5, learnable=False), LinearPosition(2, sigma=0.42**0.5, learnable=False),
                     p_survival=1.0, p_detection=p_detection, clutter_intensity=clutter, birth_weight=0.0,
                     capacity=8, learnable=False).double()
    joint = JointSensorPMB(filt, ConstantVelocity(2, q=0.1, learnable=False).double(), gnss_sigma=0.96)
    return filt, joint


def one_track_state(filt: PMBFilter, mean: torch.Tensor, cov: torch.Tensor, r: float = 1.0):
    s = filt.init_state((), undetected_weight=0.0)
    return s._replace(existence=s.existence.index_put((torch.tensor([0]),), torch.tensor([r], dtype=F64)),
                      mean=s.mean.index_put((torch.tensor([0]),), mean[None]),
                      cov=s.cov.index_put((torch.tensor([0]),), cov[None]),
                      label=s.label.index_put((torch.tensor([0]),), torch.tensor([0])),
                      next_label=torch.tensor(1))


def test_joint_update_with_a_certain_association_is_the_exact_joint_kalman_update():
    filt, joint = make(p_detection=1.0, clutter=0.0)
    xs = torch.tensor([0.3, -0.2, 0.0, 0.1], dtype=F64)
    Ps = torch.diag(torch.tensor([0.5, 0.7, 0.05, 0.05], dtype=F64))
    mf = torch.tensor([20.0, 5.0, 1.0, 0.0], dtype=F64)
    Pf = torch.tensor([[0.8, 0.1, 0.2, 0.0], [0.1, 0.6, 0.0, 0.1], [0.2, 0.0, 0.4, 0.0], [0.0, 0.1, 0.0, 0.4]],
                      dtype=F64)
    state = one_track_state(filt, mf, Pf)
    z = torch.tensor([[19.1, 5.9]], dtype=F64)                   # feature minus sensor
    sensor, new_state, info = joint.v2f_update(SensorState(xs, Ps), state, z)
    assert float(info.marginals.assoc_matrix()[0, 0]) == pytest.approx(1.0, abs=1e-9)
    # the exact update of the joint Gaussian [x; f] with z = H f - H x + q
    H = torch.zeros(2, 8, dtype=F64)
    H[:, :2] = -torch.eye(2, dtype=F64)
    H[:, 4:6] = torch.eye(2, dtype=F64)
    mean = torch.cat([xs, mf])
    cov = torch.block_diag(Ps, Pf)
    exact = kalman_update(mean, cov, z[0], H, 0.42 * torch.eye(2, dtype=F64))
    torch.testing.assert_close(sensor.mean, exact.mean[:4], atol=1e-8, rtol=0)
    torch.testing.assert_close(sensor.cov, exact.cov[:4, :4], atol=1e-8, rtol=0)
    i = int((new_state.label == 0).nonzero()[0, 0])
    torch.testing.assert_close(new_state.mean[i], exact.mean[4:], atol=1e-8, rtol=0)
    torch.testing.assert_close(new_state.cov[i], exact.cov[4:, 4:], atol=1e-8, rtol=0)


def test_uncertain_association_moves_the_vehicle_less_and_misses_leave_it_alone():
    filt, joint = make(p_detection=0.9, clutter=1e-2)
    xs = torch.zeros(4, dtype=F64)
    Ps = torch.diag(torch.tensor([0.9, 0.9, 0.05, 0.05], dtype=F64))
    state = one_track_state(filt, torch.tensor([10.0, 0.0, 0.0, 0.0], dtype=F64),
                            torch.diag(torch.tensor([0.2, 0.2, 0.1, 0.1], dtype=F64)), r=0.95)
    z = torch.tensor([[9.0, 0.0]], dtype=F64)                    # says the vehicle is at +1 in x
    sure, _, _ = make(p_detection=1.0, clutter=0.0)[1].v2f_update(SensorState(xs, Ps), state, z)
    soft, _, info = joint.v2f_update(SensorState(xs, Ps), state, z)
    p = float(info.marginals.assoc_matrix()[0, 0])
    assert 0.1 < p < 1.0
    assert 0.0 < float(soft.mean[0]) < float(sure.mean[0])
    empty, _, _ = joint.v2f_update(SensorState(xs, Ps), state, torch.zeros(0, 2, dtype=F64))
    torch.testing.assert_close(empty.mean, xs, atol=1e-6, rtol=0)
    torch.testing.assert_close(empty.cov, Ps, atol=1e-6, rtol=0)


def test_inflation_with_zero_sensor_covariance_is_naive_and_gnss_update_is_a_kalman_update():
    filt, joint = make()
    state = one_track_state(filt, torch.tensor([10.0, 0.0, 0.0, 0.0], dtype=F64), torch.eye(4, dtype=F64))
    z = torch.tensor([[9.5, 0.3], [50.0, 50.0]], dtype=F64)
    s = torch.tensor([0.4, -0.1], dtype=F64)
    a, _ = v2f_update(filt, state, z, None, s, None)
    b, _ = v2f_update(filt, state, z, None, s, torch.zeros(2, 2, dtype=F64))
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y)
    c, _ = v2f_update(filt, state, z, None, s, torch.eye(2, dtype=F64))
    i = int((c.label == 0).nonzero()[0, 0])
    assert float(torch.linalg.det(c.cov[i, :2, :2])) > float(torch.linalg.det(a.cov[i, :2, :2]))
    sensor = SensorState(torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64))
    zg = torch.tensor([1.0, 2.0], dtype=F64)
    out = joint.gnss_update(sensor, zg)
    H = torch.eye(4, dtype=F64)[:2]
    ref = kalman_update(sensor.mean, sensor.cov, zg, H, 0.96**2 * torch.eye(2, dtype=F64))
    torch.testing.assert_close(out.mean, ref.mean)
    torch.testing.assert_close(out.cov, ref.cov)
    skipped = joint.gnss_update(sensor, zg, torch.tensor(False))
    torch.testing.assert_close(skipped.mean, sensor.mean)


def test_sensor_covariance_not_positive_definite_is_a_clear_error():
    filt, joint = make()
    state = one_track_state(filt, torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64))
    z = torch.tensor([[1.0, 1.0]], dtype=F64)
    bad = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=F64))
    with pytest.raises(TorchtrackError, match="sensor covariance"):
        v2f_update(filt, state, z, None, torch.zeros(4, dtype=F64), bad)
    with pytest.raises(TorchtrackError, match="sensor covariance"):
        joint.v2f_update(SensorState(torch.zeros(4, dtype=F64), bad), state, z)
    nan = torch.full((4, 4), float("nan"), dtype=F64)
    with pytest.raises(TorchtrackError, match="sensor covariance"):
        v2f_update(filt, state, z, None, torch.zeros(4, dtype=F64), nan)
