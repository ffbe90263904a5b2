"""A grey-level attribute per label for the labelled GM-PHD (feature-aided association).

Vehicles differ in tone (bright and dark ones, and many shades of each) and keep it from frame to frame;
two vehicles that pass close to each other usually do not share it. Each detection carries the grey level
``t`` measured at its centre; each label carries a running estimate ``a_ℓ`` of its vehicle's tone. In the
GM-PHD update the pair (component of label ``ℓ``, detection ``z``) is weighted by the likelihood ratio of
the detection's tone (:func:`tone_log_ratio`)::

    r(t | a_ℓ) = [(1 − ε) N(t; a_ℓ, σ_t²) + ε u] / u

against a clutter tone density ``u`` (uniform over the grey levels): the factor the attribute brings to the
measurement likelihood ``g(z | x) r(t | a_ℓ)`` when clutter has intensity ``κ(z) u``. A label without a tone
yet gets ``r = 1``. A birth's label takes its detection's tone; after each frame, each extracted estimate's
label moves its tone towards the tone of the detection nearest to it (:func:`update_tones`). The label
hand-over does not give a lost label to an estimate of a clearly different tone.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.association.grid import nearest_within
from torchtrack.filters.gmphd.filter import as_rows, labels_in
from torchtrack.filters.gmphd.labels import value_of_labels

TONE_MATCH_DISTANCE = 3.0
"""An estimate takes the tone of the nearest detection within this many px (:func:`update_tones`)."""


class LabelTones(NamedTuple):
    """Tone estimates ``tone (L,)`` of labels ``label (L,)`` (unique), each the mean of ``count (L,)`` detections'
    tones (a running mean, then an exponential one: :func:`update_tones`)."""

    label: Tensor
    tone: Tensor
    count: Tensor


def no_label_tones(dtype: torch.dtype = torch.float32, device=None) -> LabelTones:
    empty = torch.empty(0, dtype=torch.long, device=device)
    return LabelTones(empty, torch.empty(0, dtype=dtype, device=device), empty)


def lookup(tones: LabelTones, label: Tensor) -> Tensor:
    """The tone of each ``label (J,)``; NaN where the label has none."""
    unknown = torch.full(label.shape, float("nan"), dtype=tones.tone.dtype, device=label.device)
    return value_of_labels(tones.label, tones.tone, label, unknown)


def tone_log_ratio(component_tone: Tensor, detection_tone: Tensor, sigma: float, outlier: float,
                   levels: float = 256.0) -> Tensor:
    """``log r(t | a)`` for component tones ``a`` (NaN: unknown, ratio 1) and detection tones ``t`` (shapes
    broadcast: ``(G,)`` and ``(G,)`` for pairs, ``(J, 1)`` and ``(M,)`` for every pair); ``σ_t = sigma``, outlier
    probability ``ε = outlier``, clutter density ``u = 1/levels``."""
    d = detection_tone - component_tone
    log_gauss = -0.5 * (d / sigma).pow(2) - math.log(sigma * math.sqrt(2.0 * math.pi)) + math.log(levels)
    log_r = torch.logaddexp(log_gauss + math.log1p(-outlier), torch.full_like(log_gauss, math.log(outlier)))
    return torch.nan_to_num(log_r, nan=0.0)


def update_tones(tones: LabelTones, label: Tensor, position: Tensor, z: Tensor, z_tone: Tensor, rate: float,
                 max_distance: float, alive: Tensor) -> LabelTones:
    """The label tones after a frame: each estimate ``(label (E,), position (E, 2))`` with a detection of
    ``z (M, 2)`` within ``max_distance`` px moves its label's tone towards that detection's tone by
    ``max(1/(n + 1), rate)`` after ``n`` detections (the mean of the first ones, then an exponential mean);
    labels no longer in ``alive`` are forgotten."""
    known = tones
    if label.numel() and z.shape[0]:
        hit, k = nearest_within(position.to(z.dtype), z, max_distance)
        hit = as_rows(hit)
        lab, t = label[hit], z_tone[k[hit]].to(tones.tone.dtype)
        old, n = lookup(tones, lab), value_of_labels(tones.label, tones.count, lab, torch.zeros_like(lab))
        step = torch.clamp(1.0 / (n + 1).to(t.dtype), min=rate)
        new = torch.where(torch.isnan(old), t, old + step * (t - old))
        keep = as_rows(~labels_in(tones.label, lab))
        known = LabelTones(torch.cat([tones.label[keep], lab]), torch.cat([tones.tone[keep], new]),
                           torch.cat([tones.count[keep], n + 1]))
    alive_rows = as_rows(labels_in(known.label, alive))
    return LabelTones(known.label[alive_rows], known.tone[alive_rows], known.count[alive_rows])


def add_births(tones: LabelTones, label: Tensor, tone: Tensor) -> LabelTones:
    """``tones`` with the new labels ``label (B,)`` of births from detections of grey level ``tone (B,)``."""
    return LabelTones(torch.cat([tones.label, label]), torch.cat([tones.tone, tone.to(tones.tone.dtype)]),
                      torch.cat([tones.count, torch.ones_like(label)]))
