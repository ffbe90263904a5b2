"""Adaptive measurement-driven birth for the GLMB (the birth of Reuter, Vo, Vo & Dietmayer, "The labeled
multi-Bernoulli filter", IEEE TSP 62(12) 2014, as the satellite paper's GLMB uses it): every measurement of frame
``k`` proposes a birth row for frame ``k + 1`` whose existence grows with how badly the tracks explain it,

    r_B(z) = min(r_max, λ_B · (1 − r_U(z)) / max(1, Σ_{z'} (1 − r_U(z')))),     r_U(z) = Σ_h w_h [z ∈ h]   (B1)

(``λ_B``: expected births per frame; ``r_U``: the probability that ``z`` was assigned to a track). Reuter et al.
divide by ``Σ (1 − r_U)`` alone; with every measurement explained that sum is tiny and the last sliver of an
explained measurement would be born with ``r_max`` — the ``max(1, ·)`` keeps ``r_B ≤ λ_B (1 − r_U)``. Rows with
``r_B < r_min`` are not proposed. The density is ``N([z, v], diag(σ_p², σ_p², σ_v², σ_v²))`` with ``v`` the
detector's velocity (``σ_v`` its noise) where given, else ``v = 0`` with a wide ``σ_v``.

A fixed ``λ_B`` is a property of the scene's size: spread over the ~1250 unexplained measurements of a frame with
1000 vehicles it leaves every row below ``r_min`` and no track ever starts. So ``λ_B`` follows the area the frame's
detections span,

    λ_B = max(λ_0, ρ_B · A),     A = (max_z x − min_z x)(max_z y − min_z y) / 10⁶                          (B2)

(``ρ_B``: expected births per frame per megapixel; ``λ_0``: the least rate, for scenes of a few detections whose
box is nearly empty). At constant density ``A`` grows with the number of measurements, so each unexplained
measurement keeps the same ``r_B`` at any scene size.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.filters.glmb import Births


def scene_birth_rate(z: Tensor, least_rate: float, rate_per_megapixel: float) -> float:
    """Expected births per frame (B2) for the frame's detections ``z (M, 2)`` in px."""
    if z.shape[0] < 2:
        return least_rate
    extent = z.detach().amax(0) - z.detach().amin(0)
    return max(least_rate, rate_per_megapixel * float(extent[0] * extent[1]) * 1e-6)


def adaptive_births(z: Tensor, velocity: Tensor | None, used: Tensor, frame: int, next_index: int,
                    birth_rate: float, r_max: float, r_min: float, sigma_pos: float, sigma_vel: float,
                    sigma_vel_detector: float) -> Births:
    """The birth rows (B1) from ``z (M, 2)``, ``velocity (M, 2)`` or None and ``used (M,)`` ``r_U``; labels
    ``(frame, next_index + b)``. No gradient flows into ``used`` (a selection)."""
    free = (1.0 - used.detach()).clamp_min(0.0)
    r = (birth_rate * free / free.sum().clamp_min(1.0)).clamp_max(r_max)
    keep = r >= r_min
    zb, r = z[keep], r[keep]
    B = zb.shape[0]
    if velocity is not None:
        vb, sv = velocity[keep], sigma_vel_detector
    else:
        vb, sv = torch.zeros_like(zb), sigma_vel
    std = torch.tensor([sigma_pos, sigma_pos, sv, sv], dtype=z.dtype, device=z.device)
    label = torch.stack([torch.full((B,), frame, dtype=torch.long, device=z.device),
                         torch.arange(next_index, next_index + B, dtype=torch.long, device=z.device)], 1)
    return Births(torch.cat([zb, vb], 1), torch.diag(std**2).expand(B, 4, 4).clone(), torch.log(r), label)


def no_births(dtype: torch.dtype, device=None) -> Births:
    """An empty set of birth rows (state size 4)."""
    return Births(torch.empty(0, 4, dtype=dtype, device=device), torch.empty(0, 4, 4, dtype=dtype, device=device),
                  torch.empty(0, dtype=dtype, device=device), torch.empty(0, 2, dtype=torch.long, device=device))
