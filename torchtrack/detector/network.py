"""A small CenterTrack-style network (Zhou, Koltun & Krähenbühl, ECCV 2020), sized for a CPU.

Input ``(B, 3, H, W)`` with ``H, W`` multiples of 16: the current frame, the previous frame (both
normalised) and the heatmap of the previous detections, all at input resolution (eq. (1) of the
enhanced GM-PHD paper: ``H_k, V_k = CT(I_k, I_{k-1}, G_{k-1})``). A 4x4 stride-4 stem (space-to-depth
and a 1x1 convolution in one) keeps every input pixel without a full-resolution convolution; a three-level
encoder-decoder (strides 4, 8, 16) gives a receptive field of about 200 px. Beyond CenterTrack's early
fusion, a small siamese encoder correlates the two frames at stride 8 (a cost volume over +-32 px, as
in optical-flow networks): it makes the velocity learnable in minutes on a CPU. The heads,
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
VELOCITY_SCALE = 8.0   # the velocity head predicts v / 8 (px/frame): unit-scale outputs train fast


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.ReLU(inplace=True))


def correlation(a: torch.Tensor, b: torch.Tensor, radius: int) -> torch.Tensor:
    """Cost volume ``C[d](p) = <a(p), b(p + d)> / C`` for all ``d`` in ``[-radius, radius]^2`` (row-major,
    ``dy`` outer): ``(B, C, h, w), (B, C, h, w) -> (B, (2r+1)^2, h, w)`` (contiguous NCHW).

    Computed on contiguous NCHW copies (the shifted products of channels-last tensors are slower); without
    autograd each shift's sum is written in place (no concatenation)."""
    a = (a / a.shape[1]).contiguous()
    b = F.pad(b.contiguous(), (radius, radius, radius, radius))
    h, w = a.shape[-2:]
    k = 2 * radius + 1
    shifts = [(dy, dx) for dy in range(k) for dx in range(k)]
    if torch.is_grad_enabled() and (a.requires_grad or b.requires_grad):
        return torch.stack([(a * b[:, :, dy:dy + h, dx:dx + w]).sum(1) for dy, dx in shifts], dim=1)
    out = a.new_empty(a.shape[0], k * k, h, w)
    for i, (dy, dx) in enumerate(shifts):
        torch.sum(a * b[:, :, dy:dy + h, dx:dx + w], 1, out=out[:, i])
    return out


def correlation_last(a: torch.Tensor, b: torch.Tensor, radius: int, block: int = 16) -> torch.Tensor:
    """:func:`correlation` without autograd, channels last: ``(B, C, h, w), (B, C, h, w) -> (B, h, w, (2r+1)^2)``.

    One batched matrix product: each block of ``block`` pixels of a row of ``a`` against the ``2r + 1`` rows of
    ``block + 2r`` pixels of ``b`` around it; the ``2r + 1`` diagonals of each row's product are its costs."""
    k, n = 2 * radius + 1, a.shape[1]
    a = a.permute(0, 2, 3, 1) / n                                               # (B, h, w, C)
    bsz, h, w, _ = a.shape
    block = math.gcd(w, block)
    b = F.pad(b, (radius, radius, radius, radius)).permute(0, 2, 3, 1).contiguous()   # (B, h + 2r, w + 2r, C)
    blocks, span, s = w // block, block + 2 * radius, b.stride()
    windows = b.as_strided((bsz, h, blocks, k, span, n), (s[0], s[1], block * n, s[1], n, 1))
    prod = torch.bmm(a.reshape(-1, block, n), windows.reshape(-1, k * span, n).transpose(1, 2))  # (., block, k span)
    costs = prod.as_strided((prod.shape[0], block, k, k), (block * k * span, k * span + 1, span, 1))
    return costs.reshape(bsz, h, w, k * k)


class CenterTrackNet(nn.Module):
    """``forward(x) -> (heatmap_logits (B,1,H/2,W/2), offset (B,2,H/2,W/2), velocity (B,2,H/2,W/2))``.

    ``widths``: channels at strides 4, 8, 16. ``head``: channels of the last convolution, whose
    ``1x1`` projection to ``5 * 4`` channels is rearranged (pixel shuffle) into the five stride-2 maps.
    ``motion``: channels of the shared (siamese) encoder of each frame whose stride-8 features are
    correlated over displacements up to ``radius`` cells (``8 radius`` px); the cost volume joins the
    main path at stride 8 and carries the motion to the velocity head.
    ``fine``: channels of the stride-2 branch (0: none), meant to resolve vehicles a few pixels apart:
    a ``3x3`` stride-2 convolution of the input (frames and prior) plus a ``1x1`` projection of the
    head features upsampled to stride 2 (the context, a U-Net skip), a ReLU, and a ``3x3`` convolution
    whose output is added to the heatmap logits and the offset.
    """

    def __init__(self, widths: tuple[int, int, int] = (32, 48, 64), head: int = 32, motion: int = 16,
                 radius: int = 4, fine: int = 0) -> None:
        super().__init__()
        c2, c3, c4 = widths
        self.widths, self.head_channels, self.radius, self.fine = tuple(widths), head, radius, fine
        k2 = (2 * radius + 1) ** 2
        # a 4x4 stride-4 convolution = space-to-depth followed by a 1x1 convolution
        self.stem = nn.Sequential(nn.Conv2d(3, c2, 4, 4), nn.ReLU(inplace=True), _conv(c2, c2), _conv(c2, c2))
        self.siamese4 = nn.Sequential(nn.Conv2d(1, motion, 4, 4), nn.ReLU(inplace=True),
                                      nn.Conv2d(motion, motion, 3, 1, 1))
        self.siamese8 = nn.Sequential(_conv(motion, motion, 2), nn.Conv2d(motion, motion, 3, 1, 1))
        self.log_temperature = nn.Parameter(torch.tensor(0.0))
        d = torch.arange(-radius, radius + 1, dtype=torch.float32) * 8.0
        grid = torch.stack(torch.meshgrid(d, d, indexing="ij"), dim=0).reshape(2, -1)   # (dy, dx)
        self.register_buffer("displacement", grid.flip(0).clone(), persistent=False)     # (2, K^2) as (dx, dy)
        self.down3 = nn.Sequential(_conv(c2, c3, 2))
        self.fuse3 = nn.Sequential(nn.Conv2d(c3 + k2, c3, 1), nn.ReLU(inplace=True), _conv(c3, c3))
        self.down4 = nn.Sequential(_conv(c3, c4, 2), _conv(c4, c4))
        self.lat4 = nn.Conv2d(c4, c3, 1)
        self.up3 = _conv(c3, c2)
        self.up2 = _conv(c2, head)
        self.heads = nn.Conv2d(head, 5 * 4, 1)
        if fine:
            self.fine_in = nn.Conv2d(3, fine, 3, 2, 1)
            self.fine_mix = nn.Conv2d(head, fine, 1)
            self.fine_out = nn.Conv2d(fine, 3, 3, 1, 1)
        self.shuffle = nn.PixelShuffle(2)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)
        nn.init.normal_(self.heads.weight, std=0.01)
        if fine:
            nn.init.normal_(self.fine_out.weight, std=0.01)   # residuals start at zero
        with torch.no_grad():
            self.heads.bias.zero_()
            self.heads.bias[:4] = -math.log((1 - 0.01) / 0.01)   # heatmap channel: about -4.6

    def forward(self, x: torch.Tensor, with_matching: bool = False):
        """``(heatmap_logits, offset, velocity)``; with ``with_matching`` also the matching logits
        ``(B, (2r+1)^2, H/8, W/8)`` (the scaled cost volume whose softmax gives the soft-argmax flow),
        supervised in training by a cross-entropy on the true displacement."""
        d2 = self.stem(x)
        f4 = self.siamese4(torch.cat([x[:, :1], x[:, 1:2]], dim=0))     # both frames in one batch
        f4 = f4 - F.avg_pool2d(f4, 3, 1, 1, count_include_pad=False)   # high-pass: keep small objects
        cur, prev = self.siamese8(f4).chunk(2, dim=0)
        cost = correlation(cur, prev, self.radius)
        # soft-argmax matching: the object at p in frame k was at p + d in frame k-1, v = -d
        logits = cost * self.log_temperature.exp()
        w = torch.softmax(logits, dim=1)
        flow = -torch.einsum("bkhw,ck->bchw", w, self.displacement)
        # fuse3's 1x1 convolution of the concatenation [down3(d2), cost], as two convolutions (no copy)
        mix, c3 = self.fuse3[0], self.widths[1]
        d3 = self.fuse3[2](F.relu(F.conv2d(self.down3(d2), mix.weight[:, :c3])
                                  + F.conv2d(cost, mix.weight[:, c3:], mix.bias)))
        d4 = self.down4(d3)
        u3 = self.up3(d3 + F.interpolate(self.lat4(d4), size=d3.shape[-2:], mode="nearest"))
        u2 = self.up2(d2 + F.interpolate(u3, size=d2.shape[-2:], mode="nearest"))
        out = self.shuffle(self.heads(u2))
        hm, off = out[:, :1], out[:, 1:3]
        if self.fine:
            ctx = F.interpolate(self.fine_mix(u2), size=out.shape[-2:], mode="nearest")
            res = self.fine_out(F.relu(self.fine_in(x) + ctx))
            hm, off = hm + res[:, :1], off + res[:, 1:3]
        flow = F.interpolate(flow, size=out.shape[-2:], mode="bilinear", align_corners=False)
        if with_matching:
            return hm, off, flow + out[:, 3:5] * VELOCITY_SCALE, logits
        return hm, off, flow + out[:, 3:5] * VELOCITY_SCALE
