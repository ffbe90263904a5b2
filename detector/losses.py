"""Training losses: penalty-reduced focal loss on the heatmap, masked L1 on offset and velocity.

Every term is normalised *per sample* and then averaged over the batch, so that the mean of the
per-rank losses under ``DistributedDataParallel`` equals the loss of the global batch exactly.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from detector.targets import Targets


def focal_loss(logits: torch.Tensor, target: torch.Tensor, alpha: float = 2.0, beta: float = 4.0) -> torch.Tensor:
    """CenterNet focal loss (Zhou et al. 2019, eq. (1)) per sample, ``(B,)``.

    ``L = -1/max(1, N) sum [ (1-p)^a log p  where y = 1 ;  (1-y)^b p^a log(1-p)  otherwise ]``,
    ``N`` the number of cells with ``y = 1``; ``log p`` via ``logsigmoid`` for stability.
    """
    pos = target.eq(1).float()
    p = torch.sigmoid(logits)
    log_p, log_1p = F.logsigmoid(logits), F.logsigmoid(-logits)
    pos_l = (1 - p) ** alpha * log_p * pos
    neg_l = (1 - target) ** beta * p ** alpha * log_1p * (1 - pos)
    dims = tuple(range(1, logits.dim()))
    n = pos.sum(dims).clamp(min=1)
    return -(pos_l.sum(dims) + neg_l.sum(dims)) / n


def masked_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-sample ``sum_mask |pred - target| / max(1, |mask|)``; pred, target (B,C,h,w), mask (B,h,w)."""
    m = mask[:, None].float()
    return ((pred - target).abs() * m).sum((1, 2, 3)) / m.sum((1, 2, 3)).clamp(min=1)


def detection_loss(outputs: tuple[torch.Tensor, torch.Tensor, torch.Tensor], targets: Targets,
                   offset_weight: float = 1.0, velocity_weight: float = 0.1) -> tuple[torch.Tensor, dict]:
    """Total loss (batch mean of per-sample sums) and its parts (detached, batch means)."""
    hm, off, vel = outputs
    l_hm = focal_loss(hm, targets.heatmap)
    l_off = masked_l1(off, targets.offset, targets.centre)
    l_vel = masked_l1(vel, targets.velocity, targets.has_velocity)
    total = (l_hm + offset_weight * l_off + velocity_weight * l_vel).mean()
    return total, {"heatmap": l_hm.mean().item(), "offset": l_off.mean().item(), "velocity": l_vel.mean().item()}
