"""Tuning the IMM: exact likelihood gradient vs finite differences; a fit moves towards the truth."""

import torch

from torchtrack.tuning.parameters import tunable_parameters
from torchtrack.tuning.trainer import Reparametrised
from torchtrack.tuning.tune import fit, get_tunable, get_values, select_trainable


def problem(runs=2, steps=15, seed=0):
    tun = get_tunable("imm", {"sigma": [0.6, 0.6, 0.6], "measurement_sigma": 300.0,
                              "transition": [[0.34, 0.33, 0.33], [0.33, 0.34, 0.33], [0.33, 0.33, 0.34]]})
    data = tun.load_data({"simulate": {"runs": runs, "steps": steps, "p_detect": 0.9}, "held_out": 2},
                         torch.Generator().manual_seed(seed))
    return tun, tun.build(), data


def test_imm_parameter_names():
    _, imm, _ = problem()
    assert set(tunable_parameters(imm)) == {"motion.sigma", "measurement.sigma", "transition.learned"}


def test_imm_likelihood_gradient_matches_finite_differences():
    tun, imm, data = problem(runs=1, steps=10)
    params = select_trainable(imm, ["transition.learned", "motion.sigma", "measurement.sigma"])
    scaled = Reparametrised(params)   # differentiate in the optimiser's own variables
    try:
        leaves = list(scaled.u.values())

        def f(*us):
            for u, v in zip(scaled.u.values(), us):
                u.data.copy_(v.detach())
            for n, p in params.items():
                p.raw = scaled.base[n] + scaled.scale[n] * dict(zip(scaled.u, us))[n]
            return tun.loss(imm, data.train, "nll")

        inputs = tuple(torch.zeros_like(u, requires_grad=True) for u in leaves)
        assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)
    finally:
        scaled.close()


def test_imm_fit_moves_noise_and_transitions_towards_the_truth():
    tun, imm, data = problem(runs=4, steps=40)
    fit(tun, imm, ["transition.learned", "measurement.sigma"], data, "nll",
        {"name": "lbfgs", "steps": 3, "max_iter": 10}, {"patience": 10}, progress=False)
    values = get_values(imm)
    assert abs(values["measurement.sigma"].item() - 100.0) < abs(300.0 - 100.0) / 3
    T = values["transition.learned"]
    # the 3g mode (the one clearly visible at sigma_w = 100 m) is found: sticky (truth 0.8, start 0.34)
    # and rarely entered from the no-manoeuvre mode (truth 0.05, start 0.33)
    assert abs(T[1, 1].item() - 0.8) < 0.15
    assert T[0, 1].item() < 0.15
