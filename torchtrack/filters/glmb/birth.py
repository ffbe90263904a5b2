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

With positions only, a birth at rest is far from a moving vehicle (WPAFB's move at a median 15 px/frame): its
first update gains little existence and its track starts frames late. The **two-point birth** takes the velocity
from the previous frame instead: each measurement ``z_j`` of frame ``k`` pairs with the (at most ``K``) nearest
measurements ``z'_i`` of frame ``k − 1`` within the maximum speed ``v_max`` (px/frame) that the tracks did not
fully explain, and each pair proposes a row

    N([z_j, z_j − z'_i], diag(σ_p², σ_p², σ_vp², σ_vp²)),
    r_B(z_j, z'_i) = r_B(z_j) · (1 − r_U(z'_i)) / max(1, Σ_{i' paired with j} (1 − r_U(z'_{i'})))          (B3)

(``r_B(z_j)`` of (B1), shared among the pairs by how unexplained the partner was; as in (B1), the ``max(1, ·)``
keeps a partner that a track nearly explains from passing on all of ``r_B(z_j)``: such a pair is most likely a
detection of a tracked vehicle and a new one, not one new vehicle. ``σ_vp`` about the std of a difference of two
detections, ``√2 σ``, plus a frame's acceleration). A measurement with no partner proposes
nothing: a track needs two consecutive detections to be born (the classic two-point initiation), which also
keeps lone clutter points from proposing rows.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchtrack.association.grid import DENSE_PAIRS, disc_candidates
from torchtrack.filters.glmb.filter import Births


def scene_birth_rate(z: Tensor, least_rate: float, rate_per_megapixel: float) -> float:
    """Expected births per frame (B2) for the frame's detections ``z (M, 2)`` in px."""
    if z.shape[0] < 2:
        return least_rate
    extent = z.detach().amax(0) - z.detach().amin(0)
    return max(least_rate, rate_per_megapixel * float(extent[0] * extent[1]) * 1e-6)


def birth_existence(used: Tensor, birth_rate: float, r_max: float) -> Tensor:
    """``r_B (M,)`` of (B1) from ``used (M,)`` ``r_U`` (no gradient flows into ``used``: a selection)."""
    free = (1.0 - used.detach()).clamp_min(0.0)
    return (birth_rate * free / free.sum().clamp_min(1.0)).clamp_max(r_max)


def _birth_rows(mean: Tensor, std: Tensor, r: Tensor, r_min: float, frame: int, next_index: int) -> Births:
    """The rows ``mean (R, 4)``, ``std (R, 4)`` (diagonal), existence ``r (R,)`` that reach ``r_min``, labelled
    ``(frame, next_index + b)`` in order."""
    keep = r >= r_min
    B = int(keep.sum())
    label = torch.stack([torch.full((B,), frame, dtype=torch.long, device=mean.device),
                         torch.arange(next_index, next_index + B, dtype=torch.long, device=mean.device)], 1)
    return Births(mean[keep], torch.diag_embed(std[keep] ** 2), torch.log(r[keep]), label)


def adaptive_births(z: Tensor, velocity: Tensor | None, used: Tensor, frame: int, next_index: int,
                    birth_rate: float, r_max: float, r_min: float, sigma_pos: float, sigma_vel: float,
                    sigma_vel_detector: float) -> Births:
    """The birth rows (B1) from ``z (M, 2)``, ``velocity (M, 2)`` or None and ``used (M,)`` ``r_U``; labels
    ``(frame, next_index + b)``."""
    r = birth_existence(used, birth_rate, r_max)
    v, sv = (velocity, sigma_vel_detector) if velocity is not None else (torch.zeros_like(z), sigma_vel)
    std = torch.tensor([sigma_pos, sigma_pos, sv, sv], dtype=z.dtype, device=z.device).expand(z.shape[0], 4)
    return _birth_rows(torch.cat([z, v], 1), std, r, r_min, frame, next_index)


def two_point_births(z: Tensor, used: Tensor, z_prev: Tensor, used_prev: Tensor, frame: int, next_index: int,
                     birth_rate: float, r_max: float, r_min: float, max_speed: float, pairs: int, sigma_pos: float,
                     sigma_vel: float) -> Births:
    """The two-point birth rows (B3) for positions only: ``z (M, 2)`` and ``used (M,)`` ``r_U`` of frame ``k``,
    ``z_prev (M', 2)`` and ``used_prev (M',)`` of frame ``k − 1``; ``sigma_vel`` the velocity std of a pair's
    birth (px/frame). Rows ordered by measurement, then by distance to the partner; labels
    ``(frame, next_index + b)``."""
    r = birth_existence(used, birth_rate, r_max)
    free_prev = (1.0 - used_prev.detach()).clamp_min(0.0)
    d, partner = _nearest_partners(z.detach(), z_prev.detach(), free_prev > 0, max_speed, pairs)   # (M, K)
    paired = torch.isfinite(d)
    share = torch.where(paired, free_prev[partner], torch.zeros_like(d))
    r_pair = r.unsqueeze(1) * share / share.sum(1, keepdim=True).clamp_min(1.0)
    z_rep = z.unsqueeze(1).expand(-1, d.shape[1], -1)
    mean = torch.cat([z_rep, z_rep - z_prev[partner]], 2).reshape(-1, 4)
    std = torch.tensor([sigma_pos, sigma_pos, sigma_vel, sigma_vel], dtype=z.dtype, device=z.device)
    return _birth_rows(mean, std.expand(mean.shape[0], 4), torch.where(paired, r_pair, 0.0).reshape(-1), r_min,
                       frame, next_index)


def _nearest_partners(z: Tensor, z_prev: Tensor, free: Tensor, max_speed: float, k: int) -> tuple[Tensor, Tensor]:
    """Distances and indices ``(M, K)``, ``K = min(k, M')``, of each of ``z (M, 2)``'s ``K`` nearest points of
    ``z_prev (M', 2)`` where ``free (M',)`` within ``max_speed``, nearest first (``inf`` where fewer). Beyond
    :data:`~torchtrack.association.grid.DENSE_PAIRS` pairs only those from the grid's cells near each point
    are measured, so a wide-area frame never forms the ``M × M'`` matrix."""
    M, P = z.shape[0], z_prev.shape[0]
    K = min(k, P)
    if M * P <= DENSE_PAIRS:
        dist = torch.cdist(z, z_prev)
        dist = torch.where((dist <= max_speed) & free, dist, torch.full_like(dist, math.inf))
        return dist.topk(K, dim=1, largest=False)
    qq, pp = disc_candidates(z, torch.full((M,), max_speed, dtype=z.dtype, device=z.device), z_prev, cell=max_speed)
    dd = (z_prev[pp] - z[qq]).norm(dim=-1)
    ok = (dd <= max_speed) & free[pp]
    qq, pp, dd = qq[ok], pp[ok], dd[ok]
    order = torch.argsort(dd, stable=True)
    order = order[torch.argsort(qq[order], stable=True)]                  # by point, then nearest first
    qq, pp, dd = qq[order], pp[order], dd[order]
    rank = torch.arange(qq.shape[0], device=z.device) - torch.searchsorted(qq, qq)
    keep = rank < K
    d = torch.full((M, K), math.inf, dtype=z.dtype, device=z.device)
    partner = torch.zeros((M, K), dtype=torch.long, device=z.device)
    d[qq[keep], rank[keep]], partner[qq[keep], rank[keep]] = dd[keep], pp[keep]
    return d, partner


def no_births(dtype: torch.dtype, device=None) -> Births:
    """An empty set of birth rows (state size 4)."""
    return Births(torch.empty(0, 4, dtype=dtype, device=device), torch.empty(0, 4, 4, dtype=dtype, device=device),
                  torch.empty(0, dtype=dtype, device=device), torch.empty(0, 2, dtype=torch.long, device=device))
