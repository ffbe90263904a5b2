"""TOMB/P filter: reduction to a Kalman filter, cardinality, labels, gradients, bad input."""

from __future__ import annotations

import math

import pytest
import torch
from filterpy.kalman import KalmanFilter as FilterpyKF

from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb.filter import PMBFilter, expected_count
from torchtrack.models import ConstantVelocity, LinearPosition

F64 = torch.float64


def make_filter(**kw) -> PMBFilter:
    args = {"p_survival": 0.99, "p_detection": 0.9, "clutter_intensity": 5 / 200**2, "birth_weight": 0.05,
            "birth_mean": torch.zeros(4), "birth_cov": torch.diag(torch.tensor([100.0**2, 100**2, 1, 1])),
            "capacity": 24}
    args.update(kw)
    learnable = args.pop("learnable", False)
    return PMBFilter(ConstantVelocity(2, q=kw.pop("q", 0.1), learnable=learnable),
                     LinearPosition(2, sigma=1.0, learnable=learnable), learnable=learnable, **args).double()


def test_reduces_to_a_kalman_filter_with_pd_one_no_clutter_one_target():
    g = torch.Generator().manual_seed(0)
    m0 = torch.tensor([1.0, -2.0, 0.5, 0.3], dtype=F64)
    P0 = torch.diag(torch.tensor([4.0, 4.0, 1.0, 1.0], dtype=F64))
    filt = make_filter(p_survival=1.0, p_detection=1.0, clutter_intensity=0.0, birth_weight=0.0)
    state = filt.init_state((), undetected_weight=1.0, undetected_mean=m0, undetected_cov=P0)
    cv = ConstantVelocity(2, q=0.1)
    ref = FilterpyKF(dim_x=4, dim_z=2)
    ref.x, ref.P = m0.numpy().copy(), P0.numpy().copy()
    ref.F = cv.transition_matrix(1.0).double().numpy()
    ref.Q = cv.process_noise(1.0).double().detach().numpy()
    ref.H = LinearPosition(2).matrix().double().numpy()
    ref.R = torch.eye(2, dtype=F64).numpy()
    x = m0.clone()
    labels = set()
    for _ in range(15):
        x = torch.cat([x[:2] + x[2:], x[2:]])
        z = (x[:2] + torch.randn(2, generator=g, dtype=F64)).unsqueeze(0)
        state, _ = filt.step(state, z, dt=1.0)
        ref.predict()
        ref.update(z[0].numpy())
        live = state.valid & (state.existence > 0.5)
        assert int(live.sum()) == 1
        i = int(live.nonzero()[0, 0])
        labels.add(int(state.label[i]))
        torch.testing.assert_close(state.mean[i].detach(), torch.from_numpy(ref.x), atol=1e-8, rtol=0)
        torch.testing.assert_close(state.cov[i].detach(), torch.from_numpy(ref.P), atol=1e-8, rtol=0)
        assert abs(float(state.existence[i]) - 1.0) < 1e-8
        assert float(expected_count(state)[0]) == pytest.approx(1.0, abs=1e-8)
    assert labels == {0}


def simulate_targets(g, runs, steps, targets, pd, clutter_per_scan, half=100.0):
    """Constant-velocity targets, detections with pd, unit noise, uniform clutter; padded sets."""
    x = targets.expand(runs, -1, -1).clone()
    zs, masks, truth = [], [], []
    for _ in range(steps):
        x = torch.cat([x[..., :2] + x[..., 2:], x[..., 2:]], -1)
        det = torch.rand(runs, x.shape[1], generator=g) < pd
        zt = x[..., :2] + torch.randn(runs, x.shape[1], 2, generator=g, dtype=F64)
        n = torch.poisson(torch.full((runs,), float(clutter_per_scan)), generator=g).long()
        C = 3 * clutter_per_scan
        zc = (2 * torch.rand(runs, C, 2, generator=g, dtype=F64) - 1) * half
        cm = torch.arange(C) < n.clamp(max=C).unsqueeze(-1)
        zs.append(torch.cat([zt, zc], 1))
        masks.append(torch.cat([det, cm], 1))
        truth.append(x.clone())
    return zs, masks, truth


def test_expected_number_of_targets_matches_truth_in_steady_state():
    g = torch.Generator().manual_seed(1)
    runs, steps = 40, 30
    targets = torch.tensor([[-40.0, 0, 1, 0], [40, 30, -1, 0], [0, -50, 0, 1]], dtype=F64)
    zs, masks, truth = simulate_targets(g, runs, steps, targets, 0.9, 5, half=100.0)
    filt = make_filter(clutter_intensity=5 / 200**2)
    state = filt.init_state((runs,), undetected_weight=3.0)
    counts, labels = [], []
    for t in range(steps):
        state, _ = filt.step(state, zs[t], masks[t], dt=1.0)
        counts.append(expected_count(state)[0])
        # label of the track nearest to target 0 in each run
        d = (state.mean[..., None, :2] - truth[t][:, None, :, :2]).norm(dim=-1)[..., 0]
        d = torch.where(filt.estimate(state).mask, d, torch.full_like(d, math.inf))
        labels.append(state.label.gather(-1, d.argmin(-1, keepdim=True)).squeeze(-1))
    per_run = torch.stack(counts[-15:]).mean(0)                   # time-average over steady state
    se = float(per_run.std() / runs**0.5)
    assert abs(float(per_run.mean()) - 3.0) < 3 * se + 0.03
    # labels are stable: the track on target 0 keeps its label in (almost) every run
    lab = torch.stack(labels[-15:])
    stable = (lab == lab[0]).all(0).float().mean()
    assert float(stable) >= 0.9


def test_gradients_flow_to_the_continuous_parameters():
    g = torch.Generator().manual_seed(2)
    targets = torch.tensor([[0.0, 0, 1, 0], [20, 5, 0, -1]], dtype=F64)
    zs, masks, _ = simulate_targets(g, 2, 6, targets, 0.9, 3, half=50.0)
    filt = make_filter(learnable=True, lbp_iterations=10, lbp_tol=None, clutter_intensity=3 / 100**2)

    def loss() -> torch.Tensor:
        state = filt.init_state((2,), undetected_weight=2.0)
        for t in range(6):
            state, _ = filt.step(state, zs[t], masks[t], dt=1.0)
        return (state.existence * state.mean[..., 0]).sum() + state.existence.sum()

    value = loss()
    value.backward()
    params = {"p_detection": filt.p_detection.raw, "p_survival": filt.p_survival.raw,
              "clutter": filt.clutter_intensity.raw, "sigma": filt.measurement.sigma.raw, "q": filt.motion.q.raw}
    for name, p in params.items():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
        assert float(p.grad.abs().sum()) > 0, name
    # central finite difference on the measurement noise (discrete selections do not move for small h)
    p = filt.measurement.sigma.raw
    h = 1e-6
    with torch.no_grad():
        p += h
        up = float(loss())
        p -= 2 * h
        down = float(loss())
        p += h
    assert float(p.grad.sum()) == pytest.approx((up - down) / (2 * h), rel=1e-4, abs=1e-7)


def test_empty_scans_prune_everything_without_nan_then_recover():
    g = torch.Generator().manual_seed(3)
    targets = torch.tensor([[0.0, 0, 1, 0]], dtype=F64)
    zs, masks, _ = simulate_targets(g, 3, 10, targets, 1.0, 0)
    filt = make_filter()
    state = filt.init_state((3,), undetected_weight=1.0)
    for t in range(10):
        state, _ = filt.step(state, zs[t], masks[t], dt=1.0)
    assert bool(filt.estimate(state).mask.any(-1).all())
    empty = torch.zeros(3, 0, 2, dtype=F64)
    for _ in range(60):
        state, info = filt.step(state, empty, dt=1.0)
        for t in state:
            if t.is_floating_point():
                assert not bool(torch.isnan(t).any())
    assert not bool(state.valid.any())                 # every Bernoulli pruned
    assert not bool(filt.estimate(state).mask.any())
    assert info.marginals.assoc.shape == (3, filt.capacity, 0)
    # all-masked scans behave like empty ones, and detections start tracks again
    state, _ = filt.step(state, torch.zeros(3, 4, 2, dtype=F64), torch.zeros(3, 4, dtype=torch.bool))
    assert not bool(state.valid.any())
    z = torch.tensor([[5.0, 5.0]], dtype=F64).expand(3, 1, 2)
    for _ in range(4):
        state, _ = filt.step(state, z, dt=1e-3)
    assert bool(filt.estimate(state).mask.any(-1).all())
    assert bool(torch.isfinite(state.existence).all())


def test_bad_input_is_a_clear_error():
    filt = make_filter()
    state = filt.init_state((2,), undetected_weight=1.0)
    with pytest.raises(TorchtrackError, match="z must be"):
        filt.update(state, torch.zeros(2, 3, 3, dtype=F64))
    with pytest.raises(TorchtrackError, match="NaN"):
        filt.update(state, torch.full((2, 1, 2), float("nan"), dtype=F64))
    with pytest.raises(TorchtrackError, match="not positive definite"):
        filt.update(state, torch.zeros(2, 1, 2, dtype=F64), extra_noise=-10 * torch.eye(2, dtype=F64))
    with pytest.raises(TorchtrackError, match="p_detection"):
        make_filter(p_detection=1.5)


def test_cached_model_constants_follow_parameter_changes():
    filt = make_filter(learnable=True)
    z = torch.tensor([[[1.0, 2.0]]], dtype=F64)
    with torch.no_grad():
        state = filt.init_state((1,), undetected_weight=1.0)
        first, _ = filt.step(state, z)
        filt.p_detection.raw += 2.0                 # an optimiser step changes the parameter in place
        filt.measurement.sigma.raw -= 0.5
        second, _ = filt.step(state, z)
    fresh = make_filter(learnable=True)
    fresh.load_state_dict(filt.state_dict())
    with torch.no_grad():
        expected, _ = fresh.step(state, z)
    assert float((first.existence - second.existence).abs().max()) > 1e-3
    torch.testing.assert_close(second.existence, expected.existence)
    torch.testing.assert_close(second.cov, expected.cov)
