"""The Bernoulli existence per label (torchtrack.filters.gmphd.existence) and the update's label support."""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.filters.gmphd.existence import LabelExistence, bernoulli_step, no_existence
from torchtrack.filters.gmphd.filter import GMPHD, MixtureState
from torchtrack.filters.trackers.options import GMPHDFilterOptions
from torchtrack.models import ConstantVelocity, LinearPosition

F64 = torch.float64


def test_bernoulli_step_is_the_bernoulli_filters_existence_update_and_likelihood():
    existence = LabelExistence(torch.tensor([4, 9]), torch.tensor([1.0, 0.5], dtype=F64))
    labels = torch.tensor([4, 7, 9])
    mass = torch.tensor([1.1, 0.3, 2.0], dtype=F64)
    support = torch.tensor([30.0, 0.0, 0.2], dtype=F64)      # Σ_z Σ_j∈ℓ p_D w_j g_j(z)/κ(z)
    pd, ps = torch.tensor(0.9, dtype=F64), torch.tensor(0.99, dtype=F64)
    total, post = bernoulli_step(existence, labels, mass, support, pd, ps)
    r_pred = [0.99 * 1.0, 0.3, 0.99 * 0.5]                     # a label without an existence starts at min(W, 1)
    expected_total, expected_r = 0.0, []
    for r, w, s in zip(r_pred, mass.tolist(), support.tolist()):
        detected = s / w                                       # p_D Σ_z g_ℓ(z)/κ(z)
        factor = 1 - r * 0.9 + r * detected
        expected_total += math.log(factor)
        expected_r.append(r * (1 - 0.9 + detected) / factor)
    assert float(total) == pytest.approx(expected_total, rel=1e-12)
    assert post.label.tolist() == [4, 7, 9] and post.r.tolist() == pytest.approx(expected_r, rel=1e-12)
    # a label missed (support 0) keeps most of an existence of 1: r p_S (1 − p_D) / (1 − r p_S p_D)
    _, missed = bernoulli_step(LabelExistence(torch.tensor([4]), torch.tensor([1.0], dtype=F64)), torch.tensor([4]),
                               torch.tensor([1.0], dtype=F64), torch.tensor([0.0], dtype=F64), pd, ps)
    assert float(missed.r) == pytest.approx(0.99 * 0.1 / (1 - 0.99 * 0.9))
    assert no_existence(F64).r.numel() == 0


def test_update_reports_each_labels_support():
    phd = GMPHD(ConstantVelocity(2, q=1.0), LinearPosition(2, sigma=1.0),
                GMPHDFilterOptions(p_detection=0.8, clutter_density=1e-3)).to(F64)
    mean = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0]], dtype=F64)
    cov = torch.eye(4, dtype=F64).expand(3, 4, 4).clone()
    weights = [0.5, 0.4, 0.7]
    state = MixtureState(torch.tensor(weights, dtype=F64).log(), mean, cov, torch.tensor([5, 5, 8]),
                         torch.ones(3, dtype=torch.bool))
    z = torch.tensor([[0.5, 0.5], [2.5, -0.5]], dtype=F64)
    with torch.no_grad():
        mats = phd.matrices()
        _, info = phd.update(state, z, mats, label_index=(torch.tensor([0, 0, 1]), 2))
    pd, kappa = float(mats.p_detection), float(mats.clutter_density)
    S = torch.eye(2, dtype=F64) * 2
    g = torch.stack([torch.distributions.MultivariateNormal(mean[j, :2], S).log_prob(z).exp() for j in range(3)])
    per_component = (pd * torch.tensor(weights, dtype=F64).unsqueeze(1) * g / kappa).sum(1)
    assert info.label_support.tolist() == pytest.approx([float(per_component[:2].sum()), float(per_component[2])],
                                                        rel=1e-8)
