"""A small CenterTrack-style network (Zhou, Koltun & Krähenbühl, ECCV 2020), sized for a CPU.

Input ``(B, 3, H, W)`` with ``H, W`` multiples of 16: the current frame, the previous frame (both
normalised) and the heatmap of the previous detections, all at input resolution (eq. (1) of the
enhanced GM-PHD paper: ``H_k, V_k = CT(I_k, I_{k-1}, G_{k-1})``). A space-to-depth stem (4x4 pixels
to 48 channels) keeps every input pixel without a full-resolution convolution; a three-level
encoder-decoder (strides 4, 8, 16) gives a receptive field of about 200 px for the motion; the heads,
computed at stride 4 and pixel-shuffled to stride 2, give the
centre heatmap logits (1 channel, bias ``-4.6`` so that the initial sigmoid is about 0.01), the
sub-pixel offset (2 channels, in output cells) and the velocity (2 channels, ``x_k - x_{k-1}`` in input
pixels per frame).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

STRIDE = 2
MULTIPLE = 16


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.ReLU(inplace=True))


class CenterTrackNet(nn.Module):
    """``forward(x) -> (heatmap_logits (B,1,H/2,W/2), offset (B,2,H/2,W/2), velocity (B,2,H/2,W/2))``.

    ``widths``: channels at strides 4, 8, 16. ``head``: channels of the last convolution, whose
    ``1x1`` projection to ``5 * 4`` channels is rearranged (pixel shuffle) into the five stride-2 maps.
    """

    def __init__(self, widths: tuple[int, int, int] = (32, 48, 64), head: int = 32, in_channels: int = 3) -> None:
        super().__init__()
        c2, c3, c4 = widths
        self.widths, self.head_channels = tuple(widths), head
        self.stem = nn.Sequential(nn.PixelUnshuffle(4), nn.Conv2d(16 * in_channels, c2, 1), nn.ReLU(inplace=True),
                                  _conv(c2, c2), _conv(c2, c2))
        self.down3 = nn.Sequential(_conv(c2, c3, 2), _conv(c3, c3))
        self.down4 = nn.Sequential(_conv(c3, c4, 2), _conv(c4, c4))
        self.lat4 = nn.Conv2d(c4, c3, 1)
        self.up3 = _conv(c3, c2)
        self.up2 = _conv(c2, head)
        self.heads = nn.Conv2d(head, 5 * 4, 1)
        self.shuffle = nn.PixelShuffle(2)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)
        nn.init.normal_(self.heads.weight, std=0.01)
        with torch.no_grad():
            self.heads.bias.zero_()
            self.heads.bias[:4] = -math.log((1 - 0.01) / 0.01)   # heatmap channel: about -4.6

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        d2 = self.stem(x)
        d3 = self.down3(d2)
        d4 = self.down4(d3)
        u3 = self.up3(d3 + F.interpolate(self.lat4(d4), size=d3.shape[-2:], mode="nearest"))
        u2 = self.up2(d2 + F.interpolate(u3, size=d2.shape[-2:], mode="nearest"))
        out = self.shuffle(self.heads(u2))
        return out[:, :1], out[:, 1:3], out[:, 3:5]
