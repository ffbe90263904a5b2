"""Peak extraction: 3x3 max-pool non-maximum suppression, score threshold, top-K (CenterNet decoding)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch.nn import functional as F


class Detections(NamedTuple):
    """Detections in input pixels (``x`` = column, ``y`` = row).

    xy: (..., K, 2) positions; score: (..., K) in (0, 1); velocity: (..., K, 2) ``x_k - x_{k-1}`` in
    px/frame; mask: (..., K) bool, valid slots (batched form; a single frame's detections are trimmed,
    all True).
    """

    xy: torch.Tensor
    score: torch.Tensor
    velocity: torch.Tensor
    mask: torch.Tensor

    def __len__(self) -> int:  # number of valid detections of a single (trimmed) frame
        return int(self.mask.sum())


def _peaks(logits: torch.Tensor, threshold: float) -> tuple[torch.Tensor, ...]:
    """The peaks of ``logits (B, h, w)``: cells whose score ``sigmoid(logit)`` equals the maximum of their 3x3
    neighbourhood (``-inf`` beyond the map) and exceeds ``threshold``, in raster order. Only the cells above the
    threshold are compared with their neighbours (a gather of 9 values each), which is much cheaper than a
    max-pool over the whole map. Returns their batch index, row, column and score ``(n,)`` each."""
    bound = (-math.inf if threshold <= 0 else math.inf if threshold >= 1
             else math.log(threshold / (1 - threshold)) - 1e-3)   # candidates; the exact test is below
    bi, cy, cx = torch.nonzero(logits > bound).unbind(1)
    padded = F.pad(logits, (1, 1, 1, 1), value=-math.inf)
    d = torch.arange(-1, 2, device=logits.device)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    nb = torch.sigmoid(padded[bi[:, None], cy[:, None] + 1 + dy.reshape(1, -1), cx[:, None] + 1 + dx.reshape(1, -1)])
    sc = nb[:, 4]
    peak = (sc >= nb.max(1).values) & (sc > threshold)
    return bi[peak], cy[peak], cx[peak], sc[peak]


def decode(heatmap_logits: torch.Tensor, offset: torch.Tensor, velocity: torch.Tensor, stride: int,
           threshold: float = 0.3, top_k: int = 1000) -> Detections:
    """Decode network outputs ``(B,1,h,w), (B,2,h,w), (B,2,h,w)`` into batched :class:`Detections`.

    A cell is a peak when its score ``sigmoid(logit)`` equals the maximum of its 3x3 neighbourhood (the
    3x3 max-pool of CenterNet) and exceeds ``threshold``; the ``top_k`` best peaks are kept
    (``K = min(top_k, h w)`` slots, best first; equal scores in raster order of their cells) and their
    position is ``(cell + offset) * stride``. Masked slots hold zeros.
    """
    b, _, h, w = heatmap_logits.shape
    logits = heatmap_logits.float().reshape(b, h, w)
    k = min(top_k, h * w)
    bi, cy, cx, sc = _peaks(logits, threshold)
    lin = cy * w + cx
    order = torch.argsort(bi.double() * 2 - sc.double(), stable=True)   # by batch, then best score first
    bi, sc, lin = bi[order], sc[order], lin[order]
    first = torch.searchsorted(bi, torch.arange(b, device=bi.device))
    rank = torch.arange(len(bi), device=bi.device) - first[bi]
    ok = rank < k
    idx = torch.zeros(b, k, dtype=torch.long, device=logits.device)
    top = torch.zeros(b, k, device=logits.device)
    idx[bi[ok], rank[ok]] = lin[ok]
    top[bi[ok], rank[ok]] = sc[ok]
    mask = top > 0                                                 # a peak scores above the threshold >= 0
    cx, cy = (idx % w).float(), torch.div(idx, w, rounding_mode="floor").float()
    off = offset.float().reshape(b, 2, -1).gather(2, idx[:, None].expand(b, 2, k))
    vel = velocity.float().reshape(b, 2, -1).gather(2, idx[:, None].expand(b, 2, k))
    xy = torch.stack([(cx + off[:, 0]) * stride, (cy + off[:, 1]) * stride], dim=-1)
    m = mask[..., None]
    return Detections(torch.where(m, xy, 0.0), top, torch.where(m, vel.transpose(1, 2), 0.0), mask)


class TopPeaks:
    """The ``k`` best peaks of one frame's maps decoded block by block (a tile's core at a time), as
    :func:`decode` finds them on the whole maps: the same peaks, scores, positions and velocities, best score
    first, equal scores in raster order of their cells, at most ``k`` (the cut where the cap binds the same).

    :meth:`add` decodes one block: the maps ``(5, h, w)`` (heatmap logits, offset, velocity) of the frame's map
    cells ``origin + (0 .. h, 0 .. w)``, holding the cells it owns, ``own = (r0, r1, c0, c1)`` in the block,
    and their 3x3 neighbours inside the frame's map (the block ends where the map does: beyond is ``-inf``, as
    :func:`decode` pads). Blocks that own disjoint cells covering the map give the whole map's peaks. The best
    ``k`` so far are kept after each block, so memory holds ``k`` peaks and one block, never the frame's maps.
    ``width``: the frame's map width, for the raster order. Equal to :func:`decode` where the block's values
    equal the whole maps' (a tile's halo holds the neighbours of its core up to float rounding).
    """

    def __init__(self, k: int, width: int, stride: int, threshold: float) -> None:
        self.k, self.width, self.stride, self.threshold = k, width, stride, threshold
        self.score = torch.zeros(0)
        self.cell = torch.zeros(0, dtype=torch.long)            # the frame's raster index of each peak's cell
        self.xy = torch.zeros(0, 2)
        self.velocity = torch.zeros(0, 2)

    def add(self, maps: torch.Tensor, origin: tuple[int, int], own: tuple[int, int, int, int]) -> None:
        maps = maps.float()
        _, cy, cx, sc = _peaks(maps[None, 0], self.threshold)
        r0, r1, c0, c1 = own
        mine = (cy >= r0) & (cy < r1) & (cx >= c0) & (cx < c1)
        cy, cx, sc = cy[mine], cx[mine], sc[mine]
        off, vel = maps[1:3, cy, cx], maps[3:5, cy, cx]
        fy, fx = cy + origin[0], cx + origin[1]
        xy = torch.stack([(fx.float() + off[0]) * self.stride, (fy.float() + off[1]) * self.stride], dim=-1)
        score, cell = torch.cat([self.score, sc]), torch.cat([self.cell, fy * self.width + fx])
        xy, velocity = torch.cat([self.xy, xy]), torch.cat([self.velocity, vel.T])
        raster = torch.argsort(cell)
        keep = raster[torch.argsort(-score[raster].double(), stable=True)[: self.k]]
        self.score, self.cell, self.xy, self.velocity = score[keep], cell[keep], xy[keep], velocity[keep]

    def detections(self) -> Detections:
        """The peaks kept, best first (a single frame's trimmed :class:`Detections`)."""
        return Detections(self.xy, self.score, self.velocity, torch.ones(len(self.score), dtype=torch.bool))
