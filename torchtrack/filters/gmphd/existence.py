"""A Bernoulli existence per label beside the labelled GM-PHD, for a predictive likelihood without the PHD's
bias in ``p_D``.

For a target that is always there the PHD mass under its label settles at ``1/p_D``, so the PHD predictive
likelihood gains nothing from a detection and loses ``log(1 − p_D)``-like terms at each miss: it prefers a low
``p_D`` even when the model is right (docs/tune.md). Treating each label as a Bernoulli (existence ``r_ℓ``,
spatial density the label's normalised components ``g_ℓ``) with Poisson clutter gives, per frame, the
likelihood of independent Bernoullis (Mahler 2007, the Bernoulli filter's measurement-set likelihood, one
factor per label)::

    log p(Z) ≈ −λ_c + Σ_z log κ(z) + Σ_ℓ log(1 − r_ℓ⁻ p_D + r_ℓ⁻ p_D Σ_z g_ℓ(z)/κ(z))

and the existence update ``r_ℓ = r_ℓ⁻ (1 − p_D + p_D s_ℓ) / (1 − r_ℓ⁻ p_D + r_ℓ⁻ p_D s_ℓ)``,
``s_ℓ = Σ_z g_ℓ(z)/κ(z)``, ``r_ℓ⁻ = p_S r_ℓ``. A detected label's factor is ``≈ r p_D s``, a missed one's
``1 − r p_D``: maximised at the detection frequency. A label without an existence yet (a birth, a label the
label fix split off) starts from its mass, ``min(W_ℓ, 1)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor

from torchtrack.filters.gmphd.labels import value_of_labels

if TYPE_CHECKING:
    from torchtrack.filters.gmphd.filter import Matrices, MixtureState


class LabelExistence(NamedTuple):
    """Posterior existence ``r (L,)`` of labels ``label (L,)`` (unique) after the last frame."""

    label: Tensor
    r: Tensor


def no_existence(dtype: torch.dtype = torch.float32, device=None) -> LabelExistence:
    return LabelExistence(torch.empty(0, dtype=torch.long, device=device), torch.empty(0, dtype=dtype, device=device))


def bernoulli_step(existence: LabelExistence, labels: Tensor, mass: Tensor, support: Tensor, p_detection: Tensor,
                   p_survival: Tensor) -> tuple[Tensor, LabelExistence]:
    """One frame: ``labels (L,)`` of the predicted mixture, their predicted masses ``W_ℓ (L,)`` and supports
    ``Σ_z Σ_{j∈ℓ} p_D w_j g_j(z)/κ(z) (L,)`` (:attr:`UpdateInfo.label_support`). Returns the frame's
    ``Σ_ℓ log(1 − r⁻ p_D + r⁻ p_D s_ℓ)`` and the posterior existences (module docstring)."""
    r_pred = value_of_labels(existence.label, p_survival * existence.r, labels, mass.clamp(max=1.0))
    detected = support / mass.clamp_min(1e-300)          # p_D Σ_z g_ℓ(z)/κ(z)
    factor = 1.0 - r_pred * p_detection + r_pred * detected
    r_post = r_pred * (1.0 - p_detection + detected) / factor
    return torch.log(factor).sum(), LabelExistence(labels, r_post)


class LabelGroups(NamedTuple):
    """The labels of a mixture: ``labels (L,)`` (sorted), each component's index ``inverse (J,)`` into them and
    each label's total weight ``mass (L,)``."""

    labels: Tensor
    inverse: Tensor
    mass: Tensor


def label_groups(state: MixtureState) -> LabelGroups:
    labels, inverse = torch.unique(state.label, return_inverse=True)
    w = torch.where(state.mask, state.log_weight.exp(), torch.zeros_like(state.log_weight))
    mass = torch.zeros(labels.shape[0], dtype=w.dtype, device=w.device).index_add(0, inverse, w)
    return LabelGroups(labels, inverse, mass)


def bernoulli_log_likelihood(existence: LabelExistence, groups: LabelGroups, support: Tensor, mats: Matrices,
                             n_measurements: int, with_velocity: bool, area: float | None
                             ) -> tuple[Tensor, LabelExistence]:
    """The frame's log-likelihood of the module docstring, ``−λ_c + M log κ + Σ_ℓ log(…)`` (``κ κ_v`` when
    the detections' velocities are measured; ``λ_c = κ · area`` when ``area`` is given), and the posterior
    existences."""
    terms, post = bernoulli_step(existence, groups.labels, groups.mass, support, mats.p_detection, mats.p_survival)
    log_kappa = mats.log_clutter + (mats.log_clutter_velocity if with_velocity else 0.0)
    log_lik = terms + log_kappa * n_measurements
    if area is not None:
        log_lik = log_lik - mats.clutter_density * area
    return log_lik, post
