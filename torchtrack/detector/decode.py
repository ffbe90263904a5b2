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


def decode(heatmap_logits: torch.Tensor, offset: torch.Tensor, velocity: torch.Tensor, stride: int,
           threshold: float = 0.3, top_k: int = 1000, rows: tuple[int, int] | None = None,
           first_row: int = 0) -> Detections:
    """Decode network outputs ``(B,1,h,w), (B,2,h,w), (B,2,h,w)`` into batched :class:`Detections`.

    A cell is a peak when its score ``sigmoid(logit)`` equals the maximum of its 3x3 neighbourhood (the
    3x3 max-pool of CenterNet) and exceeds ``threshold``; the ``top_k`` best peaks are kept
    (``K = min(top_k, h w)`` slots, best first; equal scores in raster order of their cells) and their
    position is ``(cell + offset) * stride``. Masked slots hold zeros. Only the cells above the threshold
    are compared with their neighbours (a gather of 9 values each), which is much cheaper than a max-pool
    over the whole map.

    A horizontal strip of a larger map: ``rows = (a, b)`` keeps only the peaks of map rows ``a <= row < b``
    (the other rows are their neighbours, nothing more), and ``first_row`` is the larger map's row of this
    map's row 0, so that positions are in the larger frame's pixels.
    """
    b, _, h, w = heatmap_logits.shape
    logits = heatmap_logits.float().reshape(b, h, w)
    k = min(top_k, h * w)
    bound = (-math.inf if threshold <= 0 else math.inf if threshold >= 1
             else math.log(threshold / (1 - threshold)) - 1e-3)   # candidates; the exact test is below
    cand = torch.nonzero(logits > bound)                           # (n, 3): batch, row, column
    bi, cy, cx = cand.unbind(1)
    padded = F.pad(logits, (1, 1, 1, 1), value=-math.inf)
    d = torch.arange(-1, 2, device=logits.device)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    nb = torch.sigmoid(padded[bi[:, None], cy[:, None] + 1 + dy.reshape(1, -1), cx[:, None] + 1 + dx.reshape(1, -1)])
    sc = nb[:, 4]
    peak = (sc >= nb.max(1).values) & (sc > threshold)
    if rows is not None:
        peak &= (cy >= rows[0]) & (cy < rows[1])
    bi, sc, lin = bi[peak], sc[peak], (cy * w + cx)[peak]
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
    cx, cy = (idx % w).float(), (torch.div(idx, w, rounding_mode="floor") + first_row).float()
    off = offset.float().reshape(b, 2, -1).gather(2, idx[:, None].expand(b, 2, k))
    vel = velocity.float().reshape(b, 2, -1).gather(2, idx[:, None].expand(b, 2, k))
    xy = torch.stack([(cx + off[:, 0]) * stride, (cy + off[:, 1]) * stride], dim=-1)
    m = mask[..., None]
    return Detections(torch.where(m, xy, 0.0), top, torch.where(m, vel.transpose(1, 2), 0.0), mask)
