"""Int8 inference of a trained :class:`~torchtrack.detector.network.CenterTrackNet` on the CPU (post-training
static quantisation in torch's eager mode, ``x86`` engine: oneDNN's VNNI kernels where the CPU has them).

The same weights and operations as the float network: every convolution but the heads' runs in int8 (weights per
output channel, symmetric; activations per tensor, their ranges calibrated on synthetic frames), the ReLUs fused
into the convolutions, the adds and the concatenation quantised; the stride-2 branch runs at stride 4 with its
four stride-2 cells as channels (:func:`_coarse_fine`: the same integers). In float: the siamese encoder's
high-pass, the correlation, its softmax and soft-argmax flow (small maps at strides 4 and 8), the heads' 1x1
convolution (as one matrix product: the velocity's output scale is a tenth of the heatmap logits'), and the
pixel shuffle and sums after it. Every tensor between layers is channels-last, the layout in which both the int8
kernels and the float ones are fast.

A calibration is the table ``{quantisation point: [scale, zero_point]}`` (:func:`calibrate`); with it
:func:`quantize` builds the int8 network from the float weights, deterministically, in a fraction of a second —
a checkpoint carries the table and the digest of the weights it belongs to
(:func:`torchtrack.detector.calibration.calibrated_checkpoint`, ``torchtrack quantize-detector``), not int8
tensors.
"""

from __future__ import annotations

import copy
import hashlib
import warnings
from collections.abc import Iterable

import torch
from torch import nn
from torch.nn import functional as F

try:   # torch's eager-mode quantisation, announced to move to torchao; without it the detector runs in float
    from torch.ao import quantization as tq
    from torch.ao.nn import intrinsic as nni
except ImportError:   # pragma: no cover - absent only from torch versions after the one this was built on
    tq = nni = None

from torchtrack.detector.network import VELOCITY_SCALE, CenterTrackNet, correlation_last
from torchtrack.errors import TorchtrackError

ENGINE = "x86"


def _fused(seq: nn.Module) -> list[nn.Module]:
    """The convolutions of a ``Sequential`` (nested ``Conv2d, ReLU`` pairs) as ``ConvReLU2d`` where a ReLU follows."""
    flat = [m for m in seq.modules() if isinstance(m, (nn.Conv2d, nn.ReLU))]
    out = []
    for m in flat:
        if isinstance(m, nn.ReLU):
            out[-1] = nni.ConvReLU2d(out[-1], nn.ReLU())
        else:
            out.append(copy.deepcopy(m))
    return out


class QuantisableNet(nn.Module):
    """:class:`CenterTrackNet`'s forward with quantisation points (``QuantStub``/``DeQuantStub``, ``FloatFunctional``),
    built from a trained network's weights; :func:`quantize` converts it. Every tensor between the layers is
    channels-last (the layout the int8 kernels and the float ones after them are fast in)."""

    def __init__(self, net: CenterTrackNet) -> None:
        super().__init__()
        self.radius, self.fine = net.radius, net.fine
        self.log_temperature = nn.Parameter(net.log_temperature.detach().clone(), requires_grad=False)
        self.register_buffer("displacement", net.displacement.clone(), persistent=False)
        self.quant_x, self.quant_cost = tq.QuantStub(), tq.QuantStub()
        self.stem = nn.Sequential(*_fused(net.stem))
        self.siamese4 = nn.Sequential(*_fused(net.siamese4))
        self.siamese8 = nn.Sequential(*_fused(net.siamese8))
        self.quant_frames = tq.QuantStub()
        self.dequant_f4, self.quant_f4, self.dequant_f8 = tq.DeQuantStub(), tq.QuantStub(), tq.DeQuantStub()
        self.down3 = nn.Sequential(*_fused(net.down3))
        self.cat3 = nn.quantized.FloatFunctional()
        self.fuse3 = nn.Sequential(*_fused(net.fuse3))
        self.down4 = nn.Sequential(*_fused(net.down4))
        self.lat4 = copy.deepcopy(net.lat4)
        self.add3, self.add2 = nn.quantized.FloatFunctional(), nn.quantized.FloatFunctional()
        self.up3 = nn.Sequential(*_fused(net.up3))
        self.up2 = nn.Sequential(*_fused(net.up2))
        # the heads' 1x1 convolution in float, as a matrix product of the channels-last features
        self.register_buffer("heads_weight", net.heads.weight.detach()[:, :, 0, 0].T.clone(), persistent=False)
        self.register_buffer("heads_bias", net.heads.bias.detach().clone(), persistent=False)
        self.register_buffer("box", torch.full((net.siamese8[0][0].in_channels, 1, 3, 3), 1 / 9), persistent=False)
        self.dequant_u2 = tq.DeQuantStub()
        if self.fine:
            # the stride-2 branch at stride 4, its four stride-2 cells as channels (see _coarse_fine)
            self.fine_in, self.fine_mix, self.fine_out = _coarse_fine(net)
            self.add_fine = nn.quantized.FloatFunctional()
            self.dequant_fine = tq.DeQuantStub()

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As :meth:`CenterTrackNet.forward`; ``x`` contiguous (NCHW) is read fastest."""
        xq = self.quant_x(x).contiguous(memory_format=torch.channels_last)     # the layout's copy in int8
        d2 = self.stem(xq)
        frames = x[:, :2].transpose(0, 1).reshape(-1, 1, *x.shape[-2:])         # (2B, 1, H, W): current, previous
        f4 = self.dequant_f4(self.siamese4(self.quant_frames(frames)))
        cur, prev = self.dequant_f8(self.siamese8(self.quant_f4(high_pass(f4, self.box)))).chunk(2, dim=0)
        cost = correlation_last(cur, prev, self.radius)                          # (B, h, w, K)
        w = torch.softmax(cost * self.log_temperature.exp(), dim=-1)
        flow = -(w @ self.displacement.T).permute(0, 3, 1, 2).contiguous()
        d3 = self.fuse3(self.cat3.cat([self.down3(d2), self.quant_cost(cost.permute(0, 3, 1, 2))], dim=1))
        d4 = self.down4(d3)
        u3 = self.up3(self.add3.add(d3, F.interpolate(self.lat4(d4), size=d3.shape[-2:], mode="nearest")))
        u2 = self.up2(self.add2.add(d2, F.interpolate(u3, size=d2.shape[-2:], mode="nearest")))
        heads = torch.addmm(self.heads_bias, self.dequant_u2(u2).permute(0, 2, 3, 1).flatten(0, 2), self.heads_weight)
        heads = heads.view(*u2.shape[:1], *u2.shape[2:], -1)                      # (B, H/4, W/4, 5 * 4)
        if self.fine:
            fine = self.fine_out(self.add_fine.add_relu(self.fine_in(xq), self.fine_mix(u2)))
            heads[..., :12] += self.dequant_fine(fine).permute(0, 2, 3, 1)         # heatmap and offset
        maps = _shuffle(heads)                                                     # (B, 5, H/2, W/2)
        flow = F.interpolate(flow, size=maps.shape[-2:], mode="bilinear", align_corners=False)
        return maps[:, :1], maps[:, 1:3], flow + maps[:, 3:] * VELOCITY_SCALE


def _shuffle(maps: torch.Tensor) -> torch.Tensor:
    """``F.pixel_shuffle`` by 2 of maps given channels last, ``(B, h, w, 4C)``, as one copy into ``(B, C, 2h, 2w)``."""
    b, h, w, c4 = maps.shape
    return maps.reshape(b, h, w, c4 // 4, 2, 2).permute(0, 3, 1, 4, 2, 5).reshape(b, -1, 2 * h, 2 * w)


def high_pass(f: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """``f - F.avg_pool2d(f, 3, 1, 1, count_include_pad=False)`` of channels-last ``f`` ``(B, C, h, w)``: the mean
    over the zero-padded 3x3 window (a depthwise convolution with ``box``, ``(C, 1, 3, 3)`` of 1/9) times
    ``9 / count`` (1 inside, 3/2 on the edges, 9/4 at the corners), subtracted in the channels-last layout
    (several times faster than the pooling there)."""
    c, (h, w) = f.shape[1], f.shape[-2:]
    mean = F.conv2d(f, box, None, 1, 1, 1, c)
    edge_h, edge_w = f.new_ones(h), f.new_ones(w)
    edge_h[[0, -1]], edge_w[[0, -1]] = 1.5, 1.5
    return torch.addcmul(f.permute(0, 2, 3, 1), mean.permute(0, 2, 3, 1), (edge_h[:, None] * edge_w)[..., None],
                         value=-1).permute(0, 3, 1, 2)


def _coarse_fine(net: CenterTrackNet) -> tuple[nn.Conv2d, nn.Conv2d, nn.Conv2d]:
    """The stride-2 branch's convolutions as convolutions at stride 4 whose channels ``4c + 2i + j`` are the
    channel ``c`` of the stride-2 cell ``(i, j)`` of each stride-4 cell (``F.pixel_shuffle``'s order): the same
    sums of the same products, so in int8 the same integers, with every tensor at the trunk's resolution (no
    stride-2 tensor, upsampling or pixel shuffle of its own).

    ``fine_in`` (3x3, stride 2, padding 1 on the input) -> 5x5, stride 4, padding 1: cell ``(i, j)`` reads input
    rows ``2i - 1 + ky`` of the 4-pixel block, i.e. kernel row ``2i + ky``. ``fine_mix`` (1x1 on the stride-4
    features, then nearest upsampling to stride 2) -> its rows repeated for the four cells. ``fine_out`` (3x3,
    padding 1, at stride 2) -> 3x3 at stride 4 from cell channels ``4c + 2q + r`` to ``4o + 2i + j``: the stride-2
    row ``2Y + i - 1 + ky`` is the row ``2(Y + dy) + q``, so kernel row ``ky = 2 dy + q - i + 1``."""
    c_in, c_mix, c_out = net.fine_in, net.fine_mix, net.fine_out
    f, n_in, n_out = c_in.out_channels, c_in.in_channels, c_out.out_channels
    fine_in = nn.Conv2d(n_in, 4 * f, 5, 4, 1)
    fine_mix = nn.Conv2d(c_mix.in_channels, 4 * f, 1)
    fine_out = nn.Conv2d(4 * f, 4 * n_out, 3, 1, 1)
    with torch.no_grad():
        for m in (fine_in, fine_out):
            m.weight.zero_()
        fine_in.bias.copy_(c_in.bias.repeat_interleave(4))
        fine_mix.weight.copy_(c_mix.weight.repeat_interleave(4, 0))
        fine_mix.bias.copy_(c_mix.bias.repeat_interleave(4))
        fine_out.bias.copy_(c_out.bias.repeat_interleave(4))
        for i in range(2):
            for j in range(2):
                fine_in.weight[2 * i + j::4, :, 2 * i:2 * i + 3, 2 * j:2 * j + 3] = c_in.weight
                for q in range(2):
                    for r in range(2):
                        for dy in range(3):
                            for dx in range(3):
                                ky, kx = 2 * (dy - 1) + q - i + 1, 2 * (dx - 1) + r - j + 1
                                if 0 <= ky < 3 and 0 <= kx < 3:
                                    fine_out.weight[2 * i + j::4, 2 * q + r::4, dy, dx] = c_out.weight[:, :, ky, kx]
    return (fine_in.to(memory_format=torch.channels_last), fine_mix.to(memory_format=torch.channels_last),
            fine_out.to(memory_format=torch.channels_last))


def _qconfig() -> tq.QConfig:
    return tq.QConfig(activation=tq.HistogramObserver.with_args(reduce_range=False),
                      weight=tq.PerChannelMinMaxObserver.with_args(dtype=torch.qint8,
                                                                    qscheme=torch.per_channel_symmetric))


def calibrate(net: CenterTrackNet, inputs: Iterable[torch.Tensor]) -> dict[str, list[float]]:
    """The activations' quantisation ``{quantisation point: [scale, zero_point]}`` that minimises the
    quantisation error of the histograms observed over ``inputs`` (network inputs ``(B, 3, H, W)``)."""
    torch.backends.quantized.engine = ENGINE
    model = QuantisableNet(net).eval()
    model.qconfig = _qconfig()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")    # torch's notice that its quantisation will move to torchao
        model = tq.prepare(model)
    with torch.inference_mode():
        for x in inputs:
            model(x)
    table = {}
    for name, m in model.named_modules():
        if isinstance(m, tq.ObserverBase):
            scale, zero = m.calculate_qparams()
            table[name.removesuffix(".activation_post_process")] = [float(scale), int(zero)]
    return table


def quantize(net: CenterTrackNet, table: dict[str, list[float]]) -> nn.Module:
    """The int8 network of ``net``'s weights with the activations' quantisation of ``table`` (:func:`calibrate`)."""
    torch.backends.quantized.engine = ENGINE
    model = QuantisableNet(net).eval()
    model.qconfig = tq.QConfig(activation=tq.MinMaxObserver, weight=_qconfig().weight)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")    # the observers saw no data (their parameters are replaced below), and
        model = tq.convert(tq.prepare(model))   # torch's notice that its quantisation will move to torchao
    modules = dict(model.named_modules())
    points = {name for name, m in modules.items() if hasattr(m, "scale") and hasattr(m, "zero_point")}
    if set(table) != points:
        raise TorchtrackError(f"int8 calibration does not fit the network: {len(table)} entries for "
                              f"{len(points)} quantisation points")
    for name, entry in table.items():
        try:
            scale, zero = float(entry[0]), int(entry[1])
        except (TypeError, ValueError, IndexError):
            raise TorchtrackError(f"int8 calibration: {name} is not [scale, zero_point]: {entry!r}") from None
        if not (scale > 0 and 0 <= zero <= 255):
            raise TorchtrackError(f"int8 calibration: {name} has scale {scale} and zero point {zero} (need a "
                                  "positive scale and a zero point in 0..255)")
        m = modules[name]
        if isinstance(m.scale, torch.Tensor):
            m.scale.fill_(scale)
            m.zero_point.fill_(zero)
        else:
            m.scale, m.zero_point = scale, zero
    return model.eval()


def weights_digest(state: dict[str, torch.Tensor]) -> str:
    """SHA-256 of a state dict's names and tensors' bytes: which weights a calibration belongs to."""
    h = hashlib.sha256()
    for name in sorted(state):
        h.update(name.encode())
        h.update(state[name].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def int8_unavailable(checkpoint: dict) -> str | None:
    """Why a checkpoint's weights cannot run in int8 here (``None``: they can): no calibration, one made for other
    weights, or no ``x86`` quantisation engine in this torch."""
    entry = checkpoint.get("int8")
    if not isinstance(entry, dict) or not isinstance(entry.get("table"), dict):
        return "the checkpoint has no int8 calibration (torchtrack quantize-detector adds one)"
    if entry.get("weights") != weights_digest(checkpoint["model"]):
        return "the checkpoint's int8 calibration was made for other weights (torchtrack quantize-detector renews it)"
    if tq is None or ENGINE not in torch.backends.quantized.supported_engines:
        return f"this torch has no eager-mode quantisation with the {ENGINE} engine"
    return None


def calibration_inputs(detector, video_config, seeds: Iterable[int]) -> list[torch.Tensor]:
    """The network inputs of ``detector`` (float) streamed over synthetic sequences, one per generator seed, as
    :func:`~torchtrack.detector.evaluate.evaluate_synthetic` streams them (registered where the detector is)."""
    from torchtrack.detector.evaluate import registered_motions, stream
    from torchtrack.sim.video import generate_sequence

    inputs: list[torch.Tensor] = []
    hook = detector.net.register_forward_pre_hook(lambda _, args: inputs.append(args[0].clone()))
    try:
        with torch.inference_mode():
            for seed in seeds:
                seq = list(generate_sequence(video_config, torch.Generator().manual_seed(seed)))
                motions = registered_motions([f.homography for f in seq]) if detector.config.data.register else None
                for _ in stream(detector, (f.image for f in seq), motions=motions):
                    pass
    finally:
        hook.remove()
    return inputs
