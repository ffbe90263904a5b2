"""Per-frame inference for a streaming pipeline: :class:`Detector` and :func:`load_detector`."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch import nn

from torchtrack.detector.checkpoint import load_checkpoint
from torchtrack.detector.config import DetectorConfig
from torchtrack.detector.decode import Detections, TopPeaks
from torchtrack.detector.network import MULTIPLE, STRIDE, CenterTrackNet
from torchtrack.detector.normalised import NormalisedFrame
from torchtrack.detector.quantized import int8_unavailable, quantize
from torchtrack.detector.refine import continuity_refine, refine_velocity
from torchtrack.detector.targets import gaussian_heatmap
from torchtrack.errors import TorchtrackError

DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "centertrack_small.pt"
HALO = 128
"""px of frame around each tile's core: more than the network's receptive field reaches from a cell (measured:
100 px up and left, 87 down and right, by the gradient of an output cell), a multiple of its stride 16."""


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
    (K, 2) px, ``score`` (K,), ``velocity`` (K, 2) px/frame, ``x_k - x_{k-1}``, best score first.

    ``rows = (y0, y1)`` (multiples of 16; ``y1`` may be the frame's height): only the detections whose cell
    lies in those rows, computed from the frame rows ``y0 - HALO .. y1 + HALO`` (the window of
    :meth:`strip_maps`), at most ``peaks_for`` of the strip's area; velocities are refined on the whole frames.
    Strips that partition the frame give, together, the whole frame's detections (where no strip reaches its cap).

    Memory: no frame-sized float buffer — the frames are normalised window by window
    (:class:`~torchtrack.detector.normalised.NormalisedFrame`) and each tile's peaks are decoded as it comes out
    of the network (:meth:`tiles`, :class:`~torchtrack.detector.decode.TopPeaks`).
    """

    def __init__(self, config: DetectorConfig | None = None) -> None:
        super().__init__()
        self.config = config or DetectorConfig()
        m = self.config.model
        self.net = CenterTrackNet(tuple(m.widths), m.head, m.motion, m.radius, m.fine)
        self.net = self.net.to(memory_format=torch.channels_last)
        self._int8: tuple[nn.Module, list[int]] | None = None

    def use_int8(self, table: dict[str, list[float]]) -> None:
        """Run the network in int8 on the CPU (:mod:`torchtrack.detector.quantized`) with the activations'
        quantisation ``table``, calibrated for the current weights; ``detect`` returns to the float network for
        good if those weights change afterwards (training, ``load_state_dict``)."""
        self._int8 = (quantize(self.net, table), _versions(self.net))

    @property
    def backend(self) -> str:
        """``"int8"`` or ``"float"``: how the next tile runs (int8 only on the CPU, in eval mode and with the
        weights it was calibrated for)."""
        if self._int8 is not None and _versions(self.net) != self._int8[1]:
            self._int8 = None
        net_device = next(self.net.parameters()).device
        return "int8" if self._int8 is not None and net_device.type == "cpu" and not self.net.training else "float"

    def inputs(self, frame, prev_frame=None, prev_points=None) -> tuple[NormalisedFrame, NormalisedFrame, torch.Tensor]:
        """The frames (current, previous), read normalised window by window, and the prior's points ``(N, 2)``."""
        cur = _as_frame(frame, "frame")
        prev = cur if prev_frame is None else _as_frame(prev_frame, "prev_frame")
        if prev.shape != cur.shape:
            raise TorchtrackError(f"detector: frame {tuple(cur.shape)} and prev_frame {tuple(prev.shape)} "
                                  "have different sizes")
        pts = torch.zeros(0, 2) if prev_points is None else torch.as_tensor(prev_points, dtype=torch.float32)
        if pts.dim() != 2 or pts.shape[-1] != 2:
            raise TorchtrackError(f"detector: prev_points must have shape (N, 2), got {tuple(pts.shape)}")
        ncur = NormalisedFrame(cur)
        return ncur, ncur if prev is cur else NormalisedFrame(prev), pts

    def _window(self, cur: NormalisedFrame, prev: NormalisedFrame, pts: torch.Tensor, rows: slice, cols: slice,
                shape: tuple[int, int]) -> torch.Tensor:
        """Network input ``(3, h, w)`` of the window ``rows × cols`` of the frame, zero where it passes the
        frame's size (the padding to a multiple of 16), the prior drawn in window coordinates; on the device of
        the prior's points ``pts``."""
        x = torch.zeros(3, *shape, device=pts.device)
        fh, fw = cur.frame[rows, cols].shape
        x[0, :fh, :fw], x[1, :fh, :fw] = cur[rows, cols], prev[rows, cols]
        origin = torch.tensor([cols.start, rows.start], dtype=torch.float32, device=pts.device)
        x[2, :fh, :fw] = gaussian_heatmap(pts - origin, (fh, fw), self.config.data.prior_sigma)
        return x

    def tiles(self, cur: NormalisedFrame, prev: NormalisedFrame,
              pts: torch.Tensor) -> Iterator[tuple[torch.Tensor, tuple[int, int], tuple[int, int, int, int]]]:
        """The network's five output maps (heatmap logits, offset, velocity) of the frames ``(H, W)``, one tile
        at a time: per tile the maps ``(5, m, n)`` of a block of the frame's map cells (stride 2, ``⌈H/2⌉ ×
        ⌈W/2⌉``), the block's first cell (row, column) in the frame's map, and the cells its tile owns in the
        block, ``(r0, r1, c0, c1)``. The block is the tile's core and the ring of cells around it that lie in
        the frame's map (the neighbours of the 3x3 peak test); the cores partition the map.

        A frame larger than ``tile`` (plus its halo) runs in tiles: the cores of side ``tile`` partition the
        frame (padded to a multiple of 16), each core is run with :data:`HALO` px of the frame around it —
        more than the network's receptive field reaches (about 100 px each way), at offsets that are
        multiples of its stride 16 — so the blocks equal the whole frame's maps (up to float rounding), and
        memory holds ``tile_batch`` tiles rather than the frame's activations or maps."""
        h, w = cur.shape
        hp, wp = h + (-h) % MULTIPLE, w + (-w) % MULTIPLE
        mh, mw = (h + STRIDE - 1) // STRIDE, (w + STRIDE - 1) // STRIDE
        device = next(self.net.parameters()).device   # the network's (a GPU): the inputs are drawn there, decoded here
        pts = pts.to(device)
        d = self.config.decode
        tiled = d.tile > 0 and (hp > d.tile + 2 * HALO or wp > d.tile + 2 * HALO)
        side = d.tile if tiled else max(hp, wp)                # one tile: the whole frame
        int8 = self.backend == "int8"
        runner = self._int8[0] if int8 else self.net
        groups: dict[tuple[int, int], list[tuple[slice, slice, int, int]]] = {}
        for y0 in range(0, hp, side):
            for x0 in range(0, wp, side):
                rows = slice(max(0, y0 - HALO), min(hp, y0 + side + HALO))
                cols = slice(max(0, x0 - HALO), min(wp, x0 + side + HALO))
                groups.setdefault((rows.stop - rows.start, cols.stop - cols.start), []).append((rows, cols, y0, x0))
        for shape, group in groups.items():
            for b in range(0, len(group), d.tile_batch):
                batch = group[b: b + d.tile_batch]
                x = torch.stack([self._window(cur, prev, pts, rows, cols, shape) for rows, cols, _, _ in batch])
                maps = torch.cat(runner(x if int8 else x.contiguous(memory_format=torch.channels_last)), 1).cpu()
                for m, (rows, cols, y0, x0) in zip(maps, batch):
                    cy, cx = y0 // STRIDE, x0 // STRIDE                        # the core's cells: cy .. ey, cx .. ex
                    ey, ex = min(cy + side // STRIDE, mh), min(cx + side // STRIDE, mw)
                    by, bx = max(cy - 1, 0), max(cx - 1, 0)                     # the block: the core and its ring
                    oy, ox = rows.start // STRIDE, cols.start // STRIDE
                    block = m[:, by - oy: min(ey + 1, mh) - oy, bx - ox: min(ex + 1, mw) - ox]
                    yield block, (by, bx), (cy - by, ey - by, cx - bx, ex - bx)

    def maps(self, cur: NormalisedFrame, prev: NormalisedFrame, pts: torch.Tensor) -> torch.Tensor:
        """The whole maps ``(5, ⌈H/2⌉, ⌈W/2⌉)`` of :meth:`tiles`, assembled (for inspection: :meth:`detect`
        decodes tile by tile and never holds them)."""
        h, w = cur.shape
        out = torch.empty(5, (h + STRIDE - 1) // STRIDE, (w + STRIDE - 1) // STRIDE)
        for block, (by, bx), (r0, r1, c0, c1) in self.tiles(cur, prev, pts):
            out[:, by + r0: by + r1, bx + c0: bx + c1] = block[:, r0:r1, c0:c1]
        return out

    @staticmethod
    def _strip_window(h: int, rows: tuple[int, int]) -> tuple[int, int]:
        """The frame rows ``y0 - HALO .. y1 + HALO`` (within the frame) that the strip ``rows`` is computed from."""
        y0, y1 = rows
        if not (0 <= y0 < y1 <= h and y0 % MULTIPLE == 0 and (y1 % MULTIPLE == 0 or y1 == h)):
            raise TorchtrackError(f"detector: rows {rows} must satisfy 0 <= y0 < y1 <= {h} (the frame's height), "
                                  f"y0 and y1 multiples of {MULTIPLE} (y1 may be the height)")
        return max(0, y0 - HALO), min(h, y1 + HALO)

    def strip_maps(self, cur: NormalisedFrame, prev: NormalisedFrame, pts: torch.Tensor,
                   rows: tuple[int, int]) -> tuple[torch.Tensor, tuple[int, int], int]:
        """The maps of the frame rows ``rows = (y0, y1)`` with one map row beyond each edge (the 3x3
        neighbourhood of the decoding), computed from the window of frame rows ``y0 - HALO .. y1 + HALO`` only
        (for inspection: :meth:`detect` decodes a strip tile by tile).

        Returns the maps ``(5, m, ⌈W/2⌉)``, the map rows ``(a, b)`` among them that the strip owns, and the
        frame's map row of their row 0. The window starts at a multiple of 16 and reaches :data:`HALO` px —
        more than the receptive field — past the rows kept, so they equal the whole frame's maps of
        :meth:`maps` (up to float rounding); a window that ends at the frame's bottom is padded as the frame."""
        y0, y1 = rows
        r0, r1 = self._strip_window(cur.shape[0], rows)
        window = self.maps(cur.rows(r0, r1), prev.rows(r0, r1), pts - torch.tensor([0.0, r0]))
        own0, own1 = y0 // STRIDE, (y1 + STRIDE - 1) // STRIDE               # the frame's map rows owned
        lo, hi = max(r0 // STRIDE, own0 - 1), min((r1 + STRIDE - 1) // STRIDE, own1 + 1)
        return window[:, lo - r0 // STRIDE: hi - r0 // STRIDE], (own0 - lo, own1 - lo), lo

    @torch.inference_mode()
    def detect(self, frame, prev_frame=None, prev_points=None, threshold: float | None = None,
               prev_velocity=None, rows: tuple[int, int] | None = None) -> Detections:
        cur, prev, pts = self.inputs(frame, prev_frame, prev_points)
        h, w = cur.shape
        d = self.config.decode
        y0, y1 = (0, h) if rows is None else rows
        r0, r1 = (0, h) if rows is None else self._strip_window(h, rows)
        own0, own1 = y0 // STRIDE - r0 // STRIDE, (y1 + STRIDE - 1) // STRIDE - r0 // STRIDE   # window map rows
        peaks = TopPeaks(d.peaks_for(y1 - y0, w), (w + STRIDE - 1) // STRIDE, STRIDE,
                         d.threshold if threshold is None else threshold)
        for block, (by, bx), (a, b, c0, c1) in self.tiles(cur.rows(r0, r1), prev.rows(r0, r1),
                                                           pts - torch.tensor([0.0, r0])):
            a, b = max(a, own0 - by), min(b, own1 - by)
            if a < b:
                peaks.add(block, (by + r0 // STRIDE, bx), (a, b, c0, c1))
        found = peaks.detections()
        xy, vel = found.xy, found.velocity
        if prev_frame is not None and d.refine_radius > 0:
            vel = refine_velocity(cur, prev, xy, vel, d.refine_patch, d.refine_radius, d.refine_pull)
        if prev_frame is not None and prev_points is not None and prev_velocity is not None and d.continuity_reach > 0:
            pv = torch.as_tensor(prev_velocity, dtype=torch.float32).reshape(-1, 2)
            if pv.shape != pts.shape:
                raise TorchtrackError(f"detector: prev_velocity {tuple(pv.shape)} does not match prev_points "
                                      f"{tuple(pts.shape)}")
            vel = continuity_refine(cur, prev, xy, vel, pts, pv, d.refine_patch, d.continuity_reach)
        return Detections(xy, found.score, vel, found.mask)


def _versions(net: nn.Module) -> list[int]:
    """The parameters' version counters (any in-place change of a weight moves its counter; -1 for tensors made
    under ``torch.inference_mode``, which have none and cannot be trained)."""
    return [-1 if p.is_inference() else p._version for p in net.parameters()]


BACKENDS = ("auto", "float", "int8")


def detector_from_checkpoint(data: dict, backend: str = "float") -> Detector:
    """A :class:`Detector` in eval mode from a validated checkpoint dict (see :mod:`torchtrack.detector.checkpoint`).

    ``backend``: ``"float"``, ``"int8"`` (the checkpoint's int8 calibration, :mod:`torchtrack.detector.quantized`;
    an error where it has none for these weights or the CPU has no int8 engine) or ``"auto"`` (int8 where
    possible, else float)."""
    if backend not in BACKENDS:
        raise TorchtrackError(f"detector backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
    det = Detector(data["config"])
    try:
        det.net.load_state_dict(data["model"])
    except RuntimeError as exc:
        raise TorchtrackError(f"detector checkpoint: weights do not fit the model ({str(exc)[:200]})") from exc
    det.eval()
    if backend != "float":
        why = int8_unavailable(data)
        if why is None:
            det.use_int8(data["int8"]["table"])
        elif backend == "int8":
            raise TorchtrackError(f"detector backend int8: {why}")
    return det


def load_detector(path: str | Path | None = None, tile: int | None = None, backend: str = "float") -> Detector:
    """The shipped detector (``torchtrack/detector/weights/centertrack_small.pt``) or the checkpoint at ``path``,
    in eval mode; ``tile`` replaces the checkpoint's tile side (see :meth:`Detector.maps`); ``backend`` as in
    :func:`detector_from_checkpoint` (default float: int8 is about twice as fast on one CPU core, at the same
    F1, but its tiles and strips equal the whole frame's maps only up to quantisation steps, docs/detector.md)."""
    data = load_checkpoint(DEFAULT_WEIGHTS if path is None else path)
    if tile is not None:
        config = data["config"]
        data["config"] = dataclasses.replace(config, decode=dataclasses.replace(config.decode, tile=tile))
    return detector_from_checkpoint(data, backend)
