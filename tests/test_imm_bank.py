"""Class-conditioned IMM bank against per-class IMMs and hand-computed Bayes updates."""

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.imm.bank import ClassConditionedIMM
from torchtrack.filters.imm.cv import ConstantVelocityIMM
from torchtrack.filters.imm.filter import InteractingMultipleModel
from torchtrack.gaussian import log_prob, moment_match
from torchtrack.models import LinearPosition, ModeControlInput

F64 = torch.float64
G = 9.81
CONF = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=F64)


def _bank(fast=True):
    T3 = torch.tensor([[0.95, 0.05, 0.0], [0.1, 0.8, 0.1], [0.0, 0.05, 0.95]], dtype=F64)
    T2 = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=F64)
    m1 = ModeControlInput([[0, 0], [0, 3 * G], [0, -G]], [0.5] * 3).double()
    m2 = ModeControlInput([[0, 0], [0, G]], [1.0, 1.0]).double()
    meas = LinearPosition(2, sigma=20.0).double()
    cls = ConstantVelocityIMM if fast else (lambda m, h, t: InteractingMultipleModel.from_mode_control(m, h, t))
    return ClassConditionedIMM([cls(m1, meas, T3), cls(m2, meas, T2)], CONF)


def _start(bank):
    mean = torch.tensor([[0.0, 0.0, 25.0, 0.0], [0.0, 200.0, 25.0, 0.0], [10.0, 400.0, 20.0, 5.0]], dtype=F64)
    cov = torch.diag(torch.tensor([400.0, 400.0, 25.0, 25.0], dtype=F64))
    return bank.initial_state(mean, cov, torch.tensor([[0.5, 0.5], [0.7, 0.3], [0.1, 0.9]], dtype=F64))


@pytest.mark.parametrize("fast", [True, False])
def test_class_update_is_bayes_with_imm_likelihoods_and_confusion(fast):
    bank = _bank(fast)
    state = bank.predict(_start(bank), 1.0)
    z = torch.tensor([[30.0, 10.0], [20.0, 230.0], [35.0, 380.0]], dtype=F64)
    report = torch.tensor([0, 1, 1])
    new, info = bank.update(state, z, z_class=report)
    lls = []
    for c, imm in enumerate(bank.imms):
        s, inf = imm.update(state.classes[c], z)
        lls.append(inf.log_likelihood)
        torch.testing.assert_close(new.classes[c].mean, s.mean)
    ll = torch.stack(lls, -1)
    expected = state.log_class_prob + ll + torch.log(CONF[:, report].T)
    torch.testing.assert_close(new.log_class_prob, torch.log_softmax(expected, -1))
    torch.testing.assert_close(info.log_likelihood, torch.logsumexp(expected, -1))
    # joint predictive density p(z, ĉ | track) summed by hand over classes and models
    zz = z.unsqueeze(-2)
    joint = bank.joint_log_density(state, zz, report.unsqueeze(-1)).squeeze(-1)
    terms = []
    for c, imm in enumerate(bank.imms):
        log_w, z_hat, S = imm.predicted_measurement(state.classes[c])
        comp = torch.logsumexp(log_w + log_prob(zz, z_hat, S), -1)
        terms.append(state.log_class_prob[:, c] + torch.log(CONF[c, report]) + comp)
    torch.testing.assert_close(joint, torch.logsumexp(torch.stack(terms, -1), -1))


def test_missing_measurement_keeps_class_probabilities():
    bank = _bank()
    state = bank.predict(_start(bank), 1.0)
    z = torch.full((3, 2), float("nan"), dtype=F64)
    new, info = bank.update(state, z, z_class=torch.tensor([1, 1, 1]))
    torch.testing.assert_close(new.log_class_prob, state.log_class_prob)
    assert not info.present.any()


def test_combine_and_mixtures_moments():
    bank = _bank()
    state = bank.predict(_start(bank), 1.0)
    est = bank.combine(state)
    w = torch.cat([state.log_class_prob[:, c:c + 1] + s.log_prob for c, s in enumerate(state.classes)], -1)
    mean = torch.cat([s.mean for s in state.classes], -2)
    cov = torch.cat([s.cov for s in state.classes], -3)
    m, P = moment_match(w, mean, cov)
    torch.testing.assert_close(est.mean, m)
    torch.testing.assert_close(est.cov, P)
    log_w, z_hat, S = bank.class_mixtures(state)
    assert log_w.shape == (3, 2, 3) and torch.isinf(log_w[:, 1, 2]).all()   # class 2 has 2 models: padded
    g = torch.Generator().manual_seed(0)
    zs, cls = bank.sample_measurements(state, 20000, g)
    p_report = torch.softmax(state.log_class_prob, -1) @ CONF
    torch.testing.assert_close((cls == 1).double().mean(-1), p_report[:, 1], atol=0.015, rtol=0)
    torch.testing.assert_close(zs.mean(-2), m[:, :2], atol=1.5, rtol=0)


def test_bank_bad_input():
    bank = _bank()
    mean, cov = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    with pytest.raises(TorchtrackError, match="class probabilities must sum to 1"):
        bank.initial_state(mean, cov, torch.tensor([0.6, 0.6], dtype=F64))
    with pytest.raises(TorchtrackError, match="confusion"):
        ClassConditionedIMM(list(bank.imms), torch.tensor([[0.9, 0.2], [0.1, 0.9]]))
    state = bank.predict(bank.initial_state(mean, cov), 1.0)
    with pytest.raises(TorchtrackError, match="class reports"):
        bank.update(state, torch.zeros(2, dtype=F64), z_class=torch.tensor(2))
