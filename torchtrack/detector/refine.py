"""Velocity refinement by local block matching around the network's estimate.

The velocity head gives a coarse ``v`` (px/frame); each detection's velocity is refined by matching a
``(2p+1)^2`` patch of the current frame centred on the detection against the previous frame, at the
integer displacements ``s = round(-v) + d``, ``d`` in ``[-R, R]^2`` (the object at ``r`` in frame ``k``
was at ``r + s`` in frame ``k-1``). The cost is the mean squared difference of zero-mean patches
(insensitive to gain and offset drift) plus a weak pull towards the network's estimate::

    C(s) = 1/n sum_u ((I_k(r+u) - m_k) - (I_{k-1}(r+s+u) - m_{k-1}(s)))^2 + lam |s + v|^2
         = 1/n [sum c^2 - n m_c^2 + sum t^2 - n m_t^2 - 2 (sum c t - n m_c m_t)] + lam |s + v|^2,

computed for all detections at once: one gather of a ``(2(p+R)+3)^2`` window of the previous frame per
detection, the cross term ``sum c t`` as a grouped convolution of each window with its template and the
box means by an integral image.
The minimum is refined to sub-pixel precision by a parabola through the costs of the neighbouring
displacements on each axis; the refined velocity is ``-s*``.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from torchtrack.association.grid import nearest_within

MATCH_CHUNK = 2048
"""Detections block-matched at once: the grouped convolution's workspace grows with their number (about
45 kB each), so a wide-area frame's tens of thousands are matched in chunks (the same result)."""


def _gather_windows(img, centre: torch.Tensor, half: int) -> torch.Tensor:
    """Windows ``(K, 2 half + 1, 2 half + 1)`` (float32) of ``img (H, W)`` centred on integer ``centre (K, 2)``
    (x, y), with replicated borders."""
    h, w = img.shape
    u = torch.arange(-half, half + 1, device=img.device)
    ys = (centre[:, 1, None] + u).clamp(0, h - 1)
    xs = (centre[:, 0, None] + u).clamp(0, w - 1)
    return img[ys[:, :, None], xs[:, None, :]].float()


def _box_means(x: torch.Tensor, size: int) -> torch.Tensor:
    """Means over every ``size x size`` window (valid positions) of ``x (..., L, L)`` by an integral
    image: ``(..., L - size + 1, L - size + 1)``."""
    c = F.pad(x.cumsum(-2).cumsum(-1), (1, 0, 1, 0))
    s = c[..., size:, size:] - c[..., :-size, size:] - c[..., size:, :-size] + c[..., :-size, :-size]
    return s / (size * size)


def match_cost(cur: torch.Tensor, prev: torch.Tensor, xy: torch.Tensor, velocity: torch.Tensor,
               patch: int = 3, radius: int = 5, pull: float = 0.005) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`refine_velocity` and the cost ``(K,)`` of each refined velocity (mean squared difference
    of the zero-mean patches plus the pull term; ``K >= 1``)."""
    k = xy.shape[0]
    r = torch.round(xy).long()
    s0 = torch.round(-velocity).long()                                       # (K, 2) as (sx, sy)
    tmpl = _gather_windows(cur, r, patch).reshape(k, -1)                      # (K, T)
    n = tmpl.shape[1]
    tmpl = tmpl - tmpl.mean(1, keepdim=True)
    win = _gather_windows(prev, r + s0, patch + radius + 1)[None]           # (1, K, L, L)
    size = 2 * patch + 1
    cross = F.conv2d(win, tmpl.view(k, 1, size, size), groups=k)[0]        # (K, M, M) sum c (t - m_t)
    mc, c2 = _box_means(torch.stack([win[0], win[0] * win[0]]), size)                 # (K, M, M) each
    cost = c2 - mc * mc + (tmpl * tmpl).mean(1)[:, None, None] - 2 * cross / n
    m = cost.shape[-1]                                                       # 2 R + 3
    d = torch.arange(m, device=xy.device) - (radius + 1)
    sx = s0[:, 0, None, None] + d[None, None, :]
    sy = s0[:, 1, None, None] + d[None, :, None]
    cost = cost + pull * ((sx + velocity[:, 0, None, None]) ** 2 + (sy + velocity[:, 1, None, None]) ** 2)
    best = cost[:, 1:-1, 1:-1].reshape(k, -1).argmin(1)
    by, bx = torch.div(best, m - 2, rounding_mode="floor") + 1, best % (m - 2) + 1
    idx = torch.arange(k, device=xy.device)
    c0 = cost[idx, by, bx]

    def _vertex(cm: torch.Tensor, cp: torch.Tensor) -> torch.Tensor:
        den = cm - 2 * c0 + cp
        return torch.where(den > 1e-9, 0.5 * (cm - cp) / den.clamp(min=1e-9), torch.zeros_like(den)).clamp(-0.5, 0.5)

    fx = _vertex(cost[idx, by, bx - 1], cost[idx, by, bx + 1])
    fy = _vertex(cost[idx, by - 1, bx], cost[idx, by + 1, bx])
    s = torch.stack([s0[:, 0] + d[bx] + fx, s0[:, 1] + d[by] + fy], dim=1)
    return -s.to(velocity.dtype), c0


def refine_velocity(cur: torch.Tensor, prev: torch.Tensor, xy: torch.Tensor, velocity: torch.Tensor,
                    patch: int = 3, radius: int = 5, pull: float = 0.005) -> torch.Tensor:
    """Refined velocities ``(K, 2)`` for detections ``xy (K, 2)`` (x, y) px with coarse ``velocity (K, 2)``.

    cur, prev: (H, W) frames normalised alike — tensors, or :class:`~torchtrack.detector.normalised.NormalisedFrame`
    s, which normalise only the patches read; ``patch`` = p (the patch is (2p+1)^2 px),
    ``radius`` = R (search half-width around ``round(-velocity)``), ``pull`` = lam (per px^2 of
    departure from the coarse estimate, in units of the frames' squared grey levels).
    """
    if xy.shape[0] == 0:
        return velocity.clone()
    return torch.cat([match_cost(cur, prev, p, v, patch, radius, pull)[0]
                      for p, v in zip(xy.split(MATCH_CHUNK), velocity.split(MATCH_CHUNK))])


def continuity_refine(cur: torch.Tensor, prev: torch.Tensor, xy: torch.Tensor, velocity: torch.Tensor,
                      prev_points: torch.Tensor, prev_velocity: torch.Tensor, patch: int = 3,
                      reach: float = 20.0) -> torch.Tensor:
    """Motion continuity: a detection near where a previous detection should be now,
    ``p_i + v_i`` (within ``reach`` px, the nearest one), may be that vehicle; where its velocity
    ``xy - p_i`` differs from the current one by more than 1.5 px, it is block-matched over +-2 px and
    replaces the current ``velocity`` when it explains the
    frames at least as well (the cost of :func:`match_cost` without pull, both over +-2 px). This
    resolves the aliasing of platoons, where a follower stands where its leader stood a frame earlier.

    xy, velocity (K, 2); prev_points, prev_velocity (N, 2) (non-finite rows are ignored). Returns (K, 2).
    """
    keep = torch.isfinite(prev_points).all(1) & torch.isfinite(prev_velocity).all(1)
    prev_points, prev_velocity = prev_points[keep].to(xy.dtype), prev_velocity[keep].to(xy.dtype)
    if xy.shape[0] == 0 or prev_points.shape[0] == 0:
        return velocity
    hit, k = nearest_within(xy, prev_points + prev_velocity, reach)
    cand = xy - prev_points[k]
    near = torch.nonzero(hit & ((cand - velocity).norm(dim=1) > 1.5))[:, 0]   # a different answer
    if near.numel() == 0:
        return velocity
    out = velocity.clone()
    for chunk in near.split(MATCH_CHUNK):
        _, c_now = match_cost(cur, prev, xy[chunk], velocity[chunk], patch, 2, 0.0)
        v_new, c_new = match_cost(cur, prev, xy[chunk], cand[chunk], patch, 2, 0.0)
        take = c_new <= c_now
        out[chunk[take]] = v_new[take]
    return out
