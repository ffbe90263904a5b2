"""The JTC bank of multiple-model particle filters (the JTC paper, section 3)."""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.particle.jtc import (
    PAPER_SPEED_ENVELOPES,
    MultipleModelParticleFilter,
    alias_tables,
    paper_bank,
    paper_class_models,
    paper_transition_matrix,
    speed_likelihood,
)
from torchtrack.gaussian import kalman_update, log_prob
from torchtrack.models import LinearPosition, ModeControlInput, RangeBearing

F64 = torch.float64
ENV = torch.tensor(PAPER_SPEED_ENVELOPES, dtype=F64)


def g1(v: float) -> float:
    """The paper's g_1, written out case by case."""
    if v <= 100:
        return 0.8
    if v <= 300:
        return 0.8 + (-0.7 / 200) * (v - 100)
    return 0.1


def g2(v: float) -> float:
    if v <= 150:
        return 0.1
    if v <= 650:
        return 0.1 + (0.85 / 500) * (v - 150)
    return 0.95


@pytest.mark.parametrize("v", [0.0, 99.0, 100.0, 100.5, 150.0, 200.0, 250.0, 299.9, 300.0, 300.1, 400.0,
                               649.0, 650.0, 651.0, 900.0])
def test_speed_likelihoods_match_the_paper(v):
    got = speed_likelihood(torch.tensor([v, v], dtype=F64), ENV)
    assert got[0].item() == pytest.approx(g1(v), abs=1e-12)
    assert got[1].item() == pytest.approx(g2(v), abs=1e-12)


def test_speed_likelihood_breakpoints():
    v = torch.tensor([[100.0, 150.0], [300.0, 650.0]], dtype=F64)
    assert torch.allclose(speed_likelihood(v, ENV), torch.tensor([[0.8, 0.1], [0.1, 0.95]], dtype=F64))


def test_paper_transition_matrix():
    P = paper_transition_matrix()
    assert torch.allclose(P.sum(-1), torch.ones(5, dtype=F64))
    assert torch.allclose(P.diagonal(), torch.full((5,), 0.7, dtype=F64))
    assert torch.allclose(P[1:, 0], torch.full((4,), 0.15, dtype=F64))
    off = P[1:, 1:][~torch.eye(4, dtype=torch.bool)]
    assert torch.allclose(off, torch.full_like(off, 0.05))


def test_alias_tables_reproduce_the_rows():
    P = torch.tensor([[0.7, 0.075, 0.075, 0.075, 0.075], [0.1, 0.2, 0.3, 0.4, 0.0], [0, 0, 1.0, 0, 0]], dtype=F64)
    prob, alias = alias_tables(P)
    M = P.shape[1]
    rebuilt = prob / M
    rebuilt = rebuilt.scatter_add(1, alias, (1 - prob) / M)
    assert torch.allclose(rebuilt, P, atol=1e-12)


def test_class_models():
    c1, c2 = (m.double() for m in paper_class_models())
    g = 9.81
    assert torch.allclose(c1.controls[2], torch.tensor([2 * g, -2 * g], dtype=F64))
    assert torch.allclose(c2.controls[4], torch.tensor([-5 * g, -5 * g], dtype=F64))
    assert torch.allclose(c1.sigma(), torch.full((5,), 5.5, dtype=F64))
    assert torch.allclose(c2.sigma(), torch.tensor([7.5, 17.5, 17.5, 17.5, 17.5], dtype=F64))


def _straight_run(runs: int, scans: int, seed: int = 0):
    """A 250 m/s straight flight 30 km from the radar, measured by the paper's radar."""
    x0 = torch.tensor([-20_000.0, 25_000.0, 250.0, 0.0], dtype=F64)
    t = torch.arange(1, scans + 1, dtype=F64) * 5.0
    truth = torch.stack([x0[0] + 250.0 * t, x0[1].expand_as(t)], -1)
    radar = RangeBearing((0.0, 0.0), 100.0, math.radians(0.15), learnable=False)
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(scans, runs, 2, generator=g, dtype=F64) * torch.tensor([100.0, math.radians(0.15)], dtype=F64)
    z = radar.measure(truth).unsqueeze(1) + noise
    cov = torch.diag(torch.tensor([150.0, 150.0, 20.0, 20.0], dtype=F64) ** 2)
    return z, x0.expand(runs, 4), cov, truth


def test_class_probabilities_normalised_and_recursion():
    """P(c | Z^k) ∝ L(c) P(c | Z^{k−1}) with L(c) the (speed-weighted) particle likelihood, normalised."""
    z, mean, cov, truth = _straight_run(3, 12)
    bank = paper_bank(400, speed_constraints=True, warmup=3).double()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        state = bank.init(mean, cov, g)
        tables = bank.tables(F64, 1)
        for k in range(1, 13):
            prev = state
            state, out = bank.step(state, z[k - 1], 5.0, k, bank.draw((3,), g, F64), tables)
            assert torch.allclose(out.class_prob.sum(-1), torch.ones(3, dtype=F64))
            assert torch.allclose(out.mode_prob.sum(-1), torch.ones(3, 2, dtype=F64))
            step_ll = state.log_likelihood - prev.log_likelihood
            expect = torch.softmax(prev.log_class + step_ll, -1)
            assert torch.allclose(out.class_prob, expect, atol=1e-12)
            if k > 3:   # the speed factor g_c(v̂_{k−1}) is part of L(c) after the warm-up
                no_speed = step_ll - torch.log(speed_likelihood(prev.speed, ENV))
                assert not torch.allclose(step_ll, no_speed)
    err = (out.mean[:, :2] - truth[-1]).norm(dim=-1)
    assert (err < 500).all()


def test_speed_likelihoods_only_after_warmup():
    z, mean, cov, _ = _straight_run(2, 8)
    outs = []
    for env in (True, False):
        bank = paper_bank(300, speed_constraints=env, warmup=4).double()
        with torch.no_grad():
            outs.append(bank.run(z, mean, cov, 5.0, torch.Generator().manual_seed(3)).class_prob)
    assert torch.allclose(outs[0][:4], outs[1][:4])
    assert not torch.allclose(outs[0][4:], outs[1][4:])


def test_mode_transitions_follow_the_markov_chain():
    """With an uninformative measurement resampling is the identity, so the modes after one step are
    draws from the transition matrix given the initial modes."""
    radar = RangeBearing((0.0, 0.0), 1e12, 1e6, learnable=False)
    P = paper_transition_matrix()
    bank = MultipleModelParticleFilter(paper_class_models(), radar, P, [0.2] * 5, 50_000).double()
    g = torch.Generator().manual_seed(0)
    mean = torch.tensor([[1e4, 1e4, 0.0, 0.0]], dtype=F64)
    with torch.no_grad():
        s0 = bank.init(mean, torch.eye(4, dtype=F64), g)
        s1, _ = bank.step(s0, torch.tensor([[1e4, 0.7]], dtype=F64), 5.0, 1, bank.draw((1,), g, F64),
                          bank.tables(F64, 1))
    pairs = s0.mode.flatten() * 5 + s1.mode.flatten()
    counts = torch.bincount(pairs, minlength=25).reshape(5, 5).double()
    freq = counts / counts.sum(-1, keepdim=True)
    se = torch.sqrt(P * (1 - P) / counts.sum(-1, keepdim=True))
    assert ((freq - P).abs() < 4 * se + 1e-3).all()


def test_single_mode_bank_matches_kalman():
    """One class, one zero-control mode and a linear sensor: the bank is a bootstrap PF for the
    linear-Gaussian CV model with Q = σ² G Gᵀ, so its mean matches the Kalman filter's."""
    sigma, dt, runs, n, T = 2.0, 1.0, 30, 4000, 8
    motion = ModeControlInput([[0.0, 0.0]], [sigma], learnable=False).double()
    meas = LinearPosition(2, sigma=3.0, learnable=False).double()
    bank = MultipleModelParticleFilter([motion], meas, [[1.0]], [1.0], n).double()
    F, Q = motion.transition_matrix(dt), motion.process_noise(dt, torch.tensor(0))
    H, R = meas.matrix(), meas.noise_cov()
    g = torch.Generator().manual_seed(0)
    m0 = torch.zeros(4, dtype=F64)
    P0 = torch.diag(torch.tensor([9.0, 9.0, 4.0, 4.0], dtype=F64))
    x, zs = m0.clone(), []
    for _ in range(T):            # data from the model itself
        x = F @ x + motion.gain(dt) @ (sigma * torch.randn(2, generator=g, dtype=F64))
        zs.append(x[:2] + 3.0 * torch.randn(2, generator=g, dtype=F64))
    z = torch.stack(zs)
    with torch.no_grad():
        out = bank.run(z.unsqueeze(1).expand(T, runs, 2), m0.expand(runs, 4), P0, dt, g)
    m, P = m0, P0
    for k in range(T):
        m, P = F @ m, F @ P @ F.T + Q
        up = kalman_update(m, P, z[k], H, R)
        m, P = up.mean, up.cov
        zscore = (out.mean[k] - m) / (P.diagonal().sqrt() / math.sqrt(n))     # (runs, 4)
        assert zscore.pow(2).mean().sqrt() < 5.0, k                          # SIR inefficiency < 25
        assert (zscore.mean(0).abs() < 4 * zscore.std(0) / math.sqrt(runs) + 0.3).all(), k   # unbiased


def test_range_bearing_fast_path_matches_the_model():
    bank = paper_bank(10).double()
    tables = bank.tables(F64, 1)
    x = torch.randn(1, 2, 10, 4, dtype=F64) * torch.tensor([5e3, 5e3, 100, 100], dtype=F64) + \
        torch.tensor([-3e4, 4e4, 0, 0], dtype=F64)
    z = torch.tensor([[5e4, -0.6]], dtype=F64)
    fast = bank.log_likelihood(x.movedim(-1, 0), z, tables) + tables.log_norm
    radar = bank.measurement
    nu = radar.residual(z[:, None, None, :], radar.measure(x))
    slow = log_prob(nu, torch.zeros_like(nu), radar.noise_cov().double())
    assert torch.allclose(fast, slow, rtol=1e-10, atol=1e-8)


def test_bank_is_differentiable_in_the_noise_levels():
    z, mean, cov, _ = _straight_run(2, 5)
    motions = paper_class_models(learnable=True)
    radar = RangeBearing((0.0, 0.0), 100.0, math.radians(0.15), learnable=True)
    bank = MultipleModelParticleFilter(motions, radar, paper_transition_matrix(), [0.6] + [0.1] * 4, 500).double()
    out = bank.run(z, mean, cov, 5.0, torch.Generator().manual_seed(0))
    grads = torch.autograd.grad(out.log_likelihood.sum(), [motions[0].sigma.raw, radar.sigma_range.raw])
    assert all(torch.isfinite(gr).all() and gr.abs().sum() > 0 for gr in grads)


def test_degenerate_measurement_keeps_estimates_finite():
    z, mean, cov, _ = _straight_run(2, 4)
    z[2, 0, 0] = math.inf                            # no particle can explain this range in run 0
    bank = paper_bank(200).double()
    with torch.no_grad():
        out = bank.run(z, mean, cov, 5.0, torch.Generator().manual_seed(0))
    assert torch.isfinite(out.mean).all() and torch.isfinite(out.class_prob).all()
    assert torch.allclose(out.class_prob[2, 0], out.class_prob[1, 0])   # prior kept on total degeneracy
    assert (out.log_likelihood[0] == -math.inf).all() and torch.isfinite(out.log_likelihood[1]).all()


def test_bad_input_raises():
    radar = RangeBearing()
    with pytest.raises(TorchtrackError, match="num_particles"):
        paper_bank(0)
    with pytest.raises(TorchtrackError, match="num_particles"):
        paper_bank(-5)
    with pytest.raises(TorchtrackError, match="same number of modes"):
        MultipleModelParticleFilter([ModeControlInput([[0.0, 0.0]], [1.0]), paper_class_models()[0]], radar,
                                    torch.eye(5), [1.0] + [0.0] * 4, 10)
    with pytest.raises(TorchtrackError, match="transition"):
        MultipleModelParticleFilter(paper_class_models(), radar, torch.full((5, 5), 0.3), [0.2] * 5, 10)
    with pytest.raises(TorchtrackError, match="class_prior"):
        MultipleModelParticleFilter(paper_class_models(), radar, paper_transition_matrix(), [0.2] * 5, 10,
                                    class_prior=[0.7, 0.7])
