"""The labelled region of a frame: a pixel rectangle ``x0 <= x < x1, y0 <= y < y1`` (x = column, y = row)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from torchtrack.errors import TorchtrackError


class Region(NamedTuple):
    """Half-open pixel rectangle ``[x0, x1) x [y0, y1)``."""

    x0: int
    y0: int
    x1: int
    y1: int

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bool: the points ``xy`` (N, 2) as (x, y) px that lie inside."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return (xy[:, 0] >= self.x0) & (xy[:, 0] < self.x1) & (xy[:, 1] >= self.y0) & (xy[:, 1] < self.y1)

    def mask(self, shape: tuple[int, int]) -> torch.Tensor:
        """(H, W) bool: the pixels inside, on a frame of ``shape`` = (H, W)."""
        out = torch.zeros(shape, dtype=torch.bool)
        out[self.y0:self.y1, self.x0:self.x1] = True
        return out


def check_region(values: Sequence[float] | None, shape: tuple[int, int], name: str = "--region") -> Region:
    """The :class:`Region` of ``values`` (x0 y0 x1 y1, whole pixels) on a frame of ``shape`` = (H, W); ``None``
    gives the whole frame. An empty rectangle or one reaching outside the frame raises naming ``name``."""
    h, w = shape
    if values is None:
        return Region(0, 0, w, h)
    if len(values) != 4 or any(float(v) != int(v) for v in values):
        raise TorchtrackError(f"{name}: expected four whole pixels x0 y0 x1 y1; got {' '.join(map(str, values))}")
    r = Region(*(int(v) for v in values))
    if r.x1 <= r.x0 or r.y1 <= r.y0:
        raise TorchtrackError(f"{name} {' '.join(map(str, r))}: empty (needs x0 < x1 and y0 < y1)")
    if r.x0 < 0 or r.y0 < 0 or r.x1 > w or r.y1 > h:
        raise TorchtrackError(f"{name} {' '.join(map(str, r))}: reaches outside the {w} x {h} frames")
    return r


def crop_start(rng: np.random.Generator, lo: int, hi: int, crop: int, size: int) -> int:
    """Random start of a ``crop``-long window on an axis of ``size`` px, as much inside ``[lo, hi)`` as
    it can be: inside it where it is at least ``crop`` long, otherwise covering it."""
    if hi - lo >= crop:
        return int(rng.integers(lo, hi - crop + 1))
    first, last = max(0, hi - crop), min(lo, size - crop)
    return int(rng.integers(first, last + 1))
