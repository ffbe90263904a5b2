"""Vehicles the truth does not list, kept out of the fine-tuning loss (``finetune.unlabelled_static``).

A truth that lists only some of the vehicles (WPAFB AOI 02: only those that move at some time) makes the
others negatives of the fine-tune, and the network learns to skip them. Before training, the starting
weights are streamed over the labelled frames (at their own threshold, registered as the pipeline
registers); a detection farther than the weights' match radius (``decode.radius``, the scoring's) from every
truth point of its frame is taken for an unlisted vehicle, and the pixels within ``finetune.unlabelled_radius``
of it become *don't-care*: neither positive nor negative (they leave
:attr:`torchtrack.detector.targets.Targets.labelled`).
"""

from __future__ import annotations

import numpy as np
import torch

from torchtrack.detector.evaluate import stream
from torchtrack.detector.labelled import LabelledFrames


@torch.inference_mode()
def unlabelled_detections(detector, data: LabelledFrames) -> list[np.ndarray]:
    """Per frame ``k`` the detections (M_k, 2) px (x, y) of ``detector`` streamed over ``data`` (the prior of
    each frame the previous detections; a registered detector gets the previous frame warped by
    ``data.motions``) that lie farther than its ``decode.radius`` from every truth point of frame ``k``."""
    registered = bool(detector.config.data.register)
    out = []
    for k, det in enumerate(stream(detector, list(data.frames), None, data.motions if registered else None)):
        xy = det.xy.numpy().astype(np.float64).reshape(-1, 2)
        truth = data.xy[k]
        if len(truth) == 0:
            out.append(xy)
            continue
        nearest = np.sqrt(((xy[:, None, :] - truth[None, :, :]) ** 2).sum(-1)).min(1)
        out.append(xy[nearest > detector.config.decode.radius])
    return out


def dont_care_mask(points: list[np.ndarray], shape: tuple[int, int], radius: float) -> torch.Tensor:
    """(T, H, W) bool: the pixels of frame ``k`` within ``radius`` px of one of ``points[k]`` (M_k, 2) (x, y)."""
    h, w = shape
    mask = np.zeros((len(points), h, w), bool)
    reach = int(np.ceil(radius))
    for k, pts in enumerate(points):
        for x, y in np.asarray(pts, np.float64).reshape(-1, 2):
            r0, r1 = max(0, int(np.floor(y)) - reach), min(h, int(np.ceil(y)) + reach + 1)
            c0, c1 = max(0, int(np.floor(x)) - reach), min(w, int(np.ceil(x)) + reach + 1)
            rows, cols = np.mgrid[r0:r1, c0:c1]
            mask[k, r0:r1, c0:c1] |= (cols - x) ** 2 + (rows - y) ** 2 <= radius ** 2
    return torch.from_numpy(mask)
