"""Training losses: penalty-reduced focal loss on the heatmap, masked L1 on offset and velocity.

Every term is normalised *per sample* and then averaged over the batch, so that the mean of the
per-rank losses under ``DistributedDataParallel`` equals the loss of the global batch exactly.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from torchtrack.detector.targets import Targets


def focal_loss(logits: torch.Tensor, target: torch.Tensor, alpha: float = 2.0, beta: float = 4.0,
               labelled: torch.Tensor | None = None) -> torch.Tensor:
    """CenterNet focal loss (Zhou et al. 2019, eq. (1)) per sample, ``(B,)``.

    ``L = -1/max(1, N) sum [ (1-p)^a log p  where y = 1 ;  (1-y)^b p^a log(1-p)  otherwise ]``,
    ``N`` the number of cells with ``y = 1``; ``log p`` via ``logsigmoid`` for stability. ``labelled``
    (B, h, w) bool, optional: the sum and ``N`` run over these cells only (unlabelled cells are
    neither positive nor negative).
    """
    keep = 1.0 if labelled is None else labelled[:, None].to(logits.dtype)
    pos = target.eq(1).float() * keep
    p = torch.sigmoid(logits)
    log_p, log_1p = F.logsigmoid(logits), F.logsigmoid(-logits)
    pos_l = (1 - p) ** alpha * log_p * pos
    neg_l = (1 - target) ** beta * p ** alpha * log_1p * (keep - pos)
    dims = tuple(range(1, logits.dim()))
    n = pos.sum(dims).clamp(min=1)
    return -(pos_l.sum(dims) + neg_l.sum(dims)) / n


def masked_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-sample ``sum_mask |pred - target| / max(1, |mask|)``; pred, target (B,C,h,w), mask (B,h,w)."""
    m = mask[:, None].float()
    return ((pred - target).abs() * m).sum((1, 2, 3)) / m.sum((1, 2, 3)).clamp(min=1)


def matching_loss(logits: torch.Tensor, velocity: torch.Tensor, mask: torch.Tensor, cell: float) -> torch.Tensor:
    """Per-sample cross-entropy of the matching logits against the true displacement, ``(B,)``.

    logits: (B, K^2, h', w') over the displacements ``d = (i - r, j - r) * cell`` px (``K = 2r + 1``,
    row-major with ``dy`` outer) at a coarser resolution than the targets; velocity (B, 2, h, w) and
    mask (B, h, w) the dense velocity targets (``h = f h'``). The object at a target cell was at
    ``-v`` in the previous frame; its label spreads bilinearly over the four bins around ``-v / cell``,
    ``L = -1/max(1, N) sum_cells sum_bins label log softmax(logits)``; displacements beyond the grid
    are not supervised.
    """
    b, k2, hc, wc = logits.shape
    k = int(round(k2 ** 0.5))
    r = (k - 1) // 2
    f = velocity.shape[-1] // wc
    logp = F.log_softmax(logits.float(), dim=1)
    logp = logp.repeat_interleave(f, dim=2).repeat_interleave(f, dim=3)          # (B, K^2, h, w)
    pos = -velocity / cell + r                                                      # bin coordinates
    ok = mask & (pos >= 0).all(1) & (pos <= k - 1).all(1)
    lo = pos.floor().clamp(0, k - 1)
    frac = pos - lo
    ce = torch.zeros(b, *mask.shape[1:], device=logits.device)
    for ox in (0, 1):
        for oy in (0, 1):
            wgt = (frac[:, 0] if ox else 1 - frac[:, 0]) * (frac[:, 1] if oy else 1 - frac[:, 1])
            ix = (lo[:, 0] + ox).clamp(max=k - 1)
            iy = (lo[:, 1] + oy).clamp(max=k - 1)
            idx = (iy * k + ix).long()[:, None]
            ce = ce - wgt * logp.gather(1, idx)[:, 0]
    okf = ok.float()
    return (ce * okf).sum((1, 2)) / okf.sum((1, 2)).clamp(min=1)


def detection_loss(outputs: tuple[torch.Tensor, ...], targets: Targets, offset_weight: float = 1.0,
                   velocity_weight: float = 0.1, match_weight: float = 0.0,
                   match_cell: float = 8.0) -> tuple[torch.Tensor, dict]:
    """Total loss (batch mean of per-sample sums) and its parts (detached, batch means).

    ``outputs``: ``(heatmap, offset, velocity)`` or, with the matching logits as a fourth element,
    the matching cross-entropy (:func:`matching_loss`, bins of ``match_cell`` px) weighted by
    ``match_weight`` is added.
    """
    hm, off, vel = outputs[:3]
    l_hm = focal_loss(hm, targets.heatmap, labelled=targets.labelled)
    l_off = masked_l1(off, targets.offset, targets.centre)
    l_vel = masked_l1(vel, targets.velocity, targets.has_velocity)
    total = l_hm + offset_weight * l_off + velocity_weight * l_vel
    parts = {"heatmap": l_hm.mean().item(), "offset": l_off.mean().item(), "velocity": l_vel.mean().item()}
    if len(outputs) > 3 and match_weight > 0:
        l_match = matching_loss(outputs[3], targets.velocity, targets.has_velocity, match_cell)
        total = total + match_weight * l_match
        parts["matching"] = l_match.mean().item()
    return total.mean(), parts
