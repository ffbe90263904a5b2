"""Per-frame inference for a streaming pipeline: :class:`Detector` and :func:`load_detector`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from torchtrack.detector.checkpoint import load_checkpoint
from torchtrack.detector.config import DetectorConfig
from torchtrack.detector.dataset import normalise
from torchtrack.detector.decode import Detections, decode
from torchtrack.detector.network import MULTIPLE, STRIDE, CenterTrackNet
from torchtrack.detector.refine import continuity_refine, refine_velocity
from torchtrack.detector.targets import gaussian_heatmap
from torchtrack.errors import TorchtrackError

DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "centertrack_small.pt"


def _as_frame(frame, name: str) -> torch.Tensor:
    t = torch.as_tensor(np.ascontiguousarray(frame)) if isinstance(frame, np.ndarray) else torch.as_tensor(frame)
    if t.dim() == 3 and t.shape[-1] in (3, 4):         # colour (H, W, C) -> grey
        t = t[..., :3].float().mean(-1)
    if t.dim() != 2:
        raise TorchtrackError(f"detector: {name} must be a grey image (H, W), got shape {tuple(t.shape)}")
    return t


class Detector(nn.Module):
    """A :class:`CenterTrackNet` with its pre- and post-processing.

    ``detect(frame, prev_frame=None, prev_points=None) -> Detections`` for one frame: ``frame`` and
    ``prev_frame`` grey ``(H, W)`` arrays or tensors of the same size (uint8 or float in 0..255;
    ``prev_frame=None`` uses ``frame``, as CenterTrack does on a first frame), ``prev_points`` ``(N, 2)``
    the previous detections (x, y) px (``None``: empty prior), ``prev_velocity`` ``(N, 2)`` their
    velocities (optional: enables the motion-continuity check of :func:`torchtrack.detector.refine.continuity_refine`;
    velocities are first refined by block matching, :func:`torchtrack.detector.refine.refine_velocity`). Returns the
    trimmed detections: ``xy``
    (K, 2) px, ``score`` (K,), ``velocity`` (K, 2) px/frame, ``x_k - x_{k-1}``.
    """

    def __init__(self, config: DetectorConfig | None = None) -> None:
        super().__init__()
        self.config = config or DetectorConfig()
        m = self.config.model
        self.net = CenterTrackNet(tuple(m.widths), m.head, m.motion, m.radius, m.fine)
        self.net = self.net.to(memory_format=torch.channels_last)

    def prepare(self, frame, prev_frame=None, prev_points=None) -> tuple[torch.Tensor, tuple[int, int]]:
        """Network input ``(1, 3, H', W')`` (padded to a multiple of 16) and the original size."""
        cur = _as_frame(frame, "frame")
        prev = cur if prev_frame is None else _as_frame(prev_frame, "prev_frame")
        if prev.shape != cur.shape:
            raise TorchtrackError(f"detector: frame {tuple(cur.shape)} and prev_frame {tuple(prev.shape)} "
                                  "have different sizes")
        h, w = cur.shape
        pts = torch.zeros(0, 2) if prev_points is None else torch.as_tensor(prev_points, dtype=torch.float32)
        if pts.dim() != 2 or pts.shape[-1] != 2:
            raise TorchtrackError(f"detector: prev_points must have shape (N, 2), got {tuple(pts.shape)}")
        prior = gaussian_heatmap(pts.reshape(-1, 2), (h, w), self.config.data.prior_sigma)
        x = torch.empty(1, h, w, 3)                       # written channels-last directly (one copy)
        x[0, ..., 0], x[0, ..., 1], x[0, ..., 2] = normalise(cur), normalise(prev), prior
        x = x.permute(0, 3, 1, 2)
        ph, pw = (-h) % MULTIPLE, (-w) % MULTIPLE
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph))
        return x.contiguous(memory_format=torch.channels_last), (h, w)

    @torch.inference_mode()
    def detect(self, frame, prev_frame=None, prev_points=None, threshold: float | None = None,
               prev_velocity=None) -> Detections:
        x, (h, w) = self.prepare(frame, prev_frame, prev_points)
        device = next(self.net.parameters()).device       # the network may sit on a GPU (training); the rest runs here
        hm, off, vel = (t.cpu() for t in self.net(x.to(device)))
        hm, off, vel = (t[..., : (h + STRIDE - 1) // STRIDE, : (w + STRIDE - 1) // STRIDE] for t in (hm, off, vel))
        d = self.config.decode
        det = decode(hm, off, vel, STRIDE, d.threshold if threshold is None else threshold, d.peaks_for(h, w))
        keep = det.mask[0]
        xy, vel = det.xy[0, keep], det.velocity[0, keep]
        if prev_frame is not None and d.refine_radius > 0:
            vel = refine_velocity(x[0, 0], x[0, 1], xy, vel, d.refine_patch, d.refine_radius, d.refine_pull)
        if prev_frame is not None and prev_points is not None and prev_velocity is not None and d.continuity_reach > 0:
            pv = torch.as_tensor(prev_velocity, dtype=torch.float32).reshape(-1, 2)
            pts = torch.as_tensor(prev_points, dtype=torch.float32).reshape(-1, 2)
            if pv.shape != pts.shape:
                raise TorchtrackError(f"detector: prev_velocity {tuple(pv.shape)} does not match prev_points "
                                      f"{tuple(pts.shape)}")
            vel = continuity_refine(x[0, 0], x[0, 1], xy, vel, pts, pv, d.refine_patch, d.continuity_reach)
        return Detections(xy, det.score[0, keep], vel, keep[keep])


def detector_from_checkpoint(data: dict) -> Detector:
    """A :class:`Detector` in eval mode from a validated checkpoint dict (see :mod:`torchtrack.detector.checkpoint`)."""
    det = Detector(data["config"])
    try:
        det.net.load_state_dict(data["model"])
    except RuntimeError as exc:
        raise TorchtrackError(f"detector checkpoint: weights do not fit the model ({str(exc)[:200]})") from exc
    return det.eval()


def load_detector(path: str | Path | None = None) -> Detector:
    """The shipped detector (``torchtrack/detector/weights/centertrack_small.pt``) or the checkpoint at ``path``,
    in eval mode."""
    return detector_from_checkpoint(load_checkpoint(DEFAULT_WEIGHTS if path is None else path))
