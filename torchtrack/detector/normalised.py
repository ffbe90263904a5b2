"""The detector's input normalisation ``(I - mean) / (std + 1)`` — the whole frame's mean and std — applied to
each window as it is read, so that a uint8 frame is never copied whole as float (a 66-megapixel frame would cost
265 MB per copy, two per frame pair).

The mean and (unbiased) std of a uint8 frame (the pipeline's) come from float64 sums of ``I`` and ``I²`` over
chunks of rows,

    mean = S1 / n,    std = sqrt((S2 - S1 · mean) / (n - 1)),

exact (integer sums below 2^53 up to 2^37 px) before the final rounding to float32; a float frame's from torch
on it as float32, as before (a float64 frame is converted whole for that, once). Each window is then converted to
float32 and normalised with the same two float32 operations the whole-frame copy used (subtract the mean, divide
by ``std + 1``), so it equals that copy's pixels bit for bit wherever the statistics agree: always for a float
frame; for a uint8 frame the std always and the mean on the synthetic frames tried (60 of 512², 3 of 4096²) but
two of three 1024² frames, where torch's float32 sum of the whole frame rounds the mean 1 ulp (4e-6) away from
the exact one.
"""

from __future__ import annotations

import torch

STATS_CHUNK = 1 << 20
"""Pixels summed at once for the statistics (8 MB of float64)."""


def frame_stats(frame: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean and unbiased std of ``frame (H, W)`` as float32 scalars: a uint8 frame's from exact sums
    (module docstring); any other frame's by torch on it as float32 (no copy of a float32 frame)."""
    if frame.dtype != torch.uint8:
        f = frame.float()
        return f.mean(), f.std()
    rows = max(1, STATS_CHUNK // max(1, frame.shape[1]))
    s1 = torch.zeros((), dtype=torch.float64, device=frame.device)
    s2 = torch.zeros_like(s1)
    for chunk in frame.split(rows):
        c = chunk.reshape(-1).double()
        s1 += c.sum()
        s2 += torch.dot(c, c)
    n = frame.numel()
    mean = s1 / n
    return mean.float(), ((s2 - s1 * mean) / (n - 1)).clamp(min=0).sqrt().float()


class NormalisedFrame:
    """A grey frame ``(H, W)`` (uint8, or float in 0..255) read through ``(I - mean) / (std + 1)`` in float32.

    Indexing gives the normalised pixels (float32) of what the same index selects in the frame — a window
    ``[rows, cols]``, the block matching's patches ``[ys, xs]`` — and nothing else is converted; :meth:`rows` is a
    band of rows that keeps the whole frame's statistics. ``shape`` and ``device`` are the frame's."""

    def __init__(self, frame: torch.Tensor, mean: torch.Tensor | None = None, std: torch.Tensor | None = None):
        self.frame = frame
        if mean is None or std is None:
            mean, std = frame_stats(frame)
        self.mean, self.std = mean, std

    @property
    def shape(self) -> torch.Size:
        return self.frame.shape

    @property
    def device(self) -> torch.device:
        return self.frame.device

    def __getitem__(self, index) -> torch.Tensor:
        return self.frame[index].to(torch.float32, copy=True).sub_(self.mean).div_(self.std + 1.0)

    def rows(self, start: int, stop: int) -> NormalisedFrame:
        """The frame's rows ``start .. stop`` with the whole frame's statistics (no copy)."""
        return NormalisedFrame(self.frame[start:stop], self.mean, self.std)
