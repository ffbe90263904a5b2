"""Particle-filter loss: smooth-case gradient vs finite differences; the stop-gradient-resampled
gradient is unbiased for the exact (Kalman) score on a linear-Gaussian model."""

import pytest
import torch

from torchtrack.tuning.parameters import get_raw, set_raw, tunable_parameters
from torchtrack.tuning.tune import get_tunable, select_trainable


def problem(sequences=2, steps=8, **opts):
    options = {"q": 2.0, "sigma": 3.0, "init_velocity_std": 10.0, "dtype": "float64", **opts}
    data = get_tunable("kalman", options).load_data(
        {"simulate": {"sequences": sequences, "steps": steps, "q": 1.0, "sigma": 2.0, "speed": 5.0}},
        torch.Generator().manual_seed(0))
    return options, data


def test_pf_loss_gradient_matches_finite_differences_without_resampling():
    options, data = problem()
    tun = get_tunable("pf", {**options, "particles": 64, "ess_threshold": 1e-12})   # never resamples
    pf = tun.build()
    select_trainable(pf, ["motion.q", "measurement.sigma"])
    tun.loss(pf, data.train, "nll").backward()
    base = get_raw(pf)
    for name, p in tunable_parameters(pf).items():
        vals = []
        for sign in (1, -1):
            set_raw(pf, {**base, name: base[name] + sign * 1e-6})
            with torch.no_grad():
                vals.append(tun.loss(pf, data.train, "nll").item())
        set_raw(pf, base)
        assert p.raw.grad.item() == pytest.approx((vals[0] - vals[1]) / 2e-6, rel=1e-5, abs=1e-8), name


def test_pf_gradient_with_resampling_is_unbiased_for_the_kalman_score():
    options, data = problem(sequences=1, steps=10)
    kal = get_tunable("kalman", options)
    kf = kal.build()
    select_trainable(kf, ["motion.q", "measurement.sigma"])
    kal.loss(kf, data.train, "nll").backward()
    exact = torch.stack([p.raw.grad for p in tunable_parameters(kf).values()])
    grads = []
    for seed in range(40):
        tun = get_tunable("pf", {**options, "particles": 400, "ess_threshold": 1.0, "seed": seed})  # resample often
        pf = tun.build()
        select_trainable(pf, ["motion.q", "measurement.sigma"])
        tun.loss(pf, data.train, "nll").backward()
        grads.append(torch.stack([p.raw.grad for p in tunable_parameters(pf).values()]))
    g = torch.stack(grads)
    mean, se = g.mean(0), g.std(0) / len(grads) ** 0.5
    assert bool(((mean - exact).abs() < 4 * se + 0.02 * exact.abs()).all()), (mean, se, exact)
