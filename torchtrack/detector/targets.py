"""Gaussian heatmaps (prior and training targets) and the dense regression targets.

Convention (input pixels, ``x`` = column, ``y`` = row): a centre ``c`` falls in output cell
``floor(c / s)`` (``s`` the stride) with sub-pixel offset ``c / s - floor(c / s)`` in ``[0, 1)``; the
heatmap target is a Gaussian ``exp(-|cell - floor(c/s)|^2 / (2 sigma^2))`` peaking at 1 in that cell
(CenterNet/CenterTrack), the element-wise maximum over objects.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


def gaussian_heatmap(points: torch.Tensor, shape: tuple[int, int], sigma: float,
                     weight: torch.Tensor | None = None) -> torch.Tensor:
    """Max over points of ``w_i exp(-|p - c_i|^2 / (2 sigma^2))`` on the pixel grid ``shape`` = (H, W).

    points: (N, 2) as (x, y) in pixels (any float); weight: optional (N,). Returns (H, W) float32,
    computed on a ``(2r+1)^2`` window (``r = ceil(3 sigma)``) around each point, no loop over points; points
    whose window misses the grid are dropped first (a tile of a large frame reaches few of the frame's points).
    """
    h, w = shape
    out = torch.zeros(h * w, dtype=torch.float32, device=points.device)
    if points.numel() == 0:
        return out.view(h, w)
    r = max(1, int(torch.ceil(torch.tensor(3.0 * sigma)).item()))
    d = torch.arange(-r, r + 1, device=points.device)
    base = torch.round(points).long()                                  # (N, 2)
    reach = ((base >= -r) & (base < torch.tensor([w + r, h + r], device=base.device))).all(1)
    if not bool(reach.all()):
        reach = reach.nonzero(as_tuple=True)[0]
        points, base = points[reach], base[reach]
        weight = None if weight is None else weight[reach]
    gx = base[:, 0, None, None] + d[None, None, :]                     # (N, 1, K)
    gy = base[:, 1, None, None] + d[None, :, None]                     # (N, K, 1)
    val = torch.exp(-((gx - points[:, 0, None, None]) ** 2 + (gy - points[:, 1, None, None]) ** 2)
                    / (2 * sigma ** 2)).float()
    if weight is not None:
        val = val * weight[:, None, None]
    gx, gy = torch.broadcast_tensors(gx, gy)
    ok = (gx >= 0) & (gx < w) & (gy >= 0) & (gy < h)
    out.scatter_reduce_(0, (gy * w + gx)[ok], val[ok], reduce="amax")
    return out.view(h, w)


class Targets(NamedTuple):
    """Dense training targets at output resolution ``(h, w) = (H/s, W/s)``.

    heatmap (1, h, w); offset (2, h, w) in cells; velocity (2, h, w) px/frame; centre (h, w) bool: a
    centre cell (offset supervised); has_velocity (h, w) bool: a centre cell with a known velocity;
    labelled (h, w) bool: a cell inside the labelled region (outside it a cell is neither positive nor
    negative: no loss term of any head reaches it).
    """

    heatmap: torch.Tensor
    offset: torch.Tensor
    velocity: torch.Tensor
    centre: torch.Tensor
    has_velocity: torch.Tensor
    labelled: torch.Tensor


def make_targets(xy: torch.Tensor, velocity: torch.Tensor, in_shape: tuple[int, int], stride: int,
                 sigma: float, labelled: torch.Tensor | None = None) -> Targets:
    """Targets for objects at ``xy`` (N, 2) px with ``velocity`` (N, 2) px/frame (NaN: unknown).

    ``labelled``: optional (H, W) bool at input resolution, the pixels whose truth is known (default: all);
    an output cell counts as labelled when all of its ``stride x stride`` pixels are. Objects anywhere
    shape the heatmap (a Gaussian tail reaches into the labelled cells), but the centre and velocity
    masks keep only labelled cells."""
    h, w = in_shape[0] // stride, in_shape[1] // stride
    if labelled is None:
        cells = torch.ones(h, w, dtype=torch.bool)
    else:
        cells = labelled[: h * stride, : w * stride].reshape(h, stride, w, stride).all(3).all(1)
    c = xy.float() / stride
    cell = torch.floor(c)
    inside = (cell[:, 0] >= 0) & (cell[:, 0] < w) & (cell[:, 1] >= 0) & (cell[:, 1] < h)
    c, cell, vel = c[inside], cell[inside].long(), velocity[inside].float()
    heat = gaussian_heatmap(cell.float(), (h, w), sigma)[None]
    idx = cell[:, 1] * w + cell[:, 0]
    offset = torch.zeros(2, h * w)
    offset[:, idx] = (c - cell).T
    known = ~torch.isnan(vel).any(dim=1)
    v = torch.zeros(2, h * w)
    v[:, idx[known]] = vel[known].T
    flat = torch.arange(h * w)
    centre = torch.isin(flat, idx)
    has_v = torch.isin(flat, idx[known])
    return Targets(heat, offset.view(2, h, w), v.view(2, h, w), centre.view(h, w) & cells,
                   has_v.view(h, w) & cells, cells)
