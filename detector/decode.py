"""Peak extraction: 3x3 max-pool non-maximum suppression, score threshold, top-K (CenterNet decoding)."""

from __future__ import annotations

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
           threshold: float = 0.3, top_k: int = 1000) -> Detections:
    """Decode network outputs ``(B,1,h,w), (B,2,h,w), (B,2,h,w)`` into batched :class:`Detections`.

    A cell is a peak when its score ``sigmoid(logit)`` equals the maximum of its 3x3 neighbourhood and
    exceeds ``threshold``; the ``top_k`` best peaks are kept (``K = min(top_k, h w)``) and their position
    is ``(cell + offset) * stride``. Masked slots hold zeros.
    """
    b, _, h, w = heatmap_logits.shape
    score = torch.sigmoid(heatmap_logits.float())
    peak = F.max_pool2d(score, 3, stride=1, padding=1) == score
    score = torch.where(peak, score, torch.zeros_like(score)).view(b, -1)
    k = min(top_k, h * w)
    top, idx = torch.topk(score, k, dim=1)
    mask = top > threshold
    cx, cy = (idx % w).float(), torch.div(idx, w, rounding_mode="floor").float()
    off = offset.float().reshape(b, 2, -1).gather(2, idx[:, None].expand(b, 2, k))
    vel = velocity.float().reshape(b, 2, -1).gather(2, idx[:, None].expand(b, 2, k))
    xy = torch.stack([(cx + off[:, 0]) * stride, (cy + off[:, 1]) * stride], dim=-1)
    m = mask[..., None]
    return Detections(torch.where(m, xy, 0.0), torch.where(mask, top, 0.0),
                      torch.where(m, vel.transpose(1, 2), 0.0), mask)
