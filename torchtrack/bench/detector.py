"""``torchtrack bench detector``: the detector's networks on one frame's tiles — the reference weights in float
(the reference) against the same weights in int8 and, given other weights, those in float and in int8.

Per frame size ``S``: a synthetic ``S × S`` sequence of two frames (the shipped generator, seed ``--seed``) is
streamed through the reference detector in float and the network inputs of its second frame are kept — the
tiles that ``Detector.detect`` runs (one window up to 1280 px, else 1024 px cores with a 128 px halo: four
1152² windows at 2048²). Every network then runs those tiles in alternation, ``repeats`` times each; the
fastest pass of each is kept, in process CPU time (what an idle core gives; the wall time of a shared machine
counts the waits) and in wall time. Frames/s is one frame's tiles per second. Float networks take the tiles
channels-last, int8 ones contiguous, as ``Detector.tiles`` gives them. Each int8 network's maps are compared
with its float network's on these inputs: the largest difference of the heatmap scores (sigmoid) over all
cells, and of the offsets (cells) and velocities (px/frame) over the cells whose float score reaches the
decoding threshold (elsewhere they are never read).

``ours_per_s`` is the fastest of the other networks (the new weights' int8 when they carry a calibration), so
``ratio`` is what replacing the reference by it gains on the network.
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchtrack.bench._timing import CLOCKS, BenchResult, load_average
from torchtrack.detector.checkpoint import load_checkpoint
from torchtrack.detector.inference import DEFAULT_WEIGHTS, detector_from_checkpoint
from torchtrack.detector.quantized import calibration_inputs, int8_unavailable
from torchtrack.errors import TorchtrackError
from torchtrack.metrics.table import format_table
from torchtrack.sim.video_config import from_dict
from torchtrack.threads import torch_threads

SIZES = (512, 2048)
REFERENCE = "reference float"


def _pass(net, tiles: list[torch.Tensor]) -> tuple[float, float]:
    """(CPU seconds, wall seconds) of ``net`` over the tiles."""
    c0, t0 = CLOCKS[1](), CLOCKS[0]()
    for x in tiles:
        net(x)
    return CLOCKS[1]() - c0, CLOCKS[0]() - t0


def _networks(data: dict, label: str) -> dict[str, tuple[torch.nn.Module, str]]:
    """``{name: (network, "float" | "int8")}`` of one loaded checkpoint: its float network and, where it carries
    a calibration, its int8 one."""
    nets = {f"{label} float": (detector_from_checkpoint(data).net, "float")}
    if int8_unavailable(data) is None:
        nets[f"{label} int8"] = (detector_from_checkpoint(data, backend="int8")._int8[0], "int8")
    return nets


def _differences(ref: list[tuple], out: list[tuple], threshold: float) -> dict[str, float]:
    """Largest differences of an int8 network's maps from its float network's (module docstring)."""
    ref, out = [torch.cat(r, 1) for r in ref], [torch.cat(o, 1) for o in out]
    score = max((a[:, :1].sigmoid() - b[:, :1].sigmoid()).abs().max().item() for a, b in zip(ref, out))
    peaks = [(a[:, :1].sigmoid() >= threshold).expand(-1, 2, -1, -1) for a in ref]
    diff = [score] + [max(float((a[:, sl] - b[:, sl]).abs()[m].max()) if m.any() else 0.0
                          for a, b, m in zip(ref, out, peaks)) for sl in (slice(1, 3), slice(3, 5))]
    return dict(zip(("heatmap_score", "offset_cells_at_peaks", "velocity_px_at_peaks"), diff))


def measure(size: int, repeats: int = 5, seed: int = 0, weights: Path | None = None, threads: int = 1,
            reference_weights: Path | None = None) -> BenchResult:
    """Frames/s of the networks (module docstring) on the tiles of one ``size × size`` frame; ``weights``: the
    other weights (None: only the reference's int8), ``reference_weights`` (None: the shipped ones)."""
    with torch_threads(threads), torch.inference_mode():
        ref_data = load_checkpoint(DEFAULT_WEIGHTS if reference_weights is None else reference_weights)
        ref = detector_from_checkpoint(ref_data)
        nets = _networks(ref_data, "reference")
        if weights is not None:
            nets.update(_networks(load_checkpoint(weights), "new"))
        if len(nets) < 2:
            raise TorchtrackError("bench detector: the reference weights carry no int8 calibration and no other "
                                  "--weights were given: nothing to compare")
        video = from_dict(dict(ref.config.data.video)).replace(width=size, height=size, frames=2)
        inputs = calibration_inputs(ref, video, [seed])
        plain = [x.contiguous() for x in inputs[len(inputs) // 2:]]
        tiles = {"int8": plain, "float": [x.contiguous(memory_format=torch.channels_last) for x in plain]}
        maps = {name: [net(x) for x in tiles[kind]] for name, (net, kind) in nets.items()}
        best = {name: [float("inf")] * 2 for name in nets}
        for net, kind in nets.values():
            _pass(net, tiles[kind])                         # warm-up
        for _ in range(repeats):
            for name, (net, kind) in nets.items():
                best[name] = [min(a, b) for a, b in zip(best[name], _pass(net, tiles[kind]))]
    threshold = ref.config.decode.threshold
    diffs = {name: _differences(maps[name.replace("int8", "float")], maps[name], threshold)
             for name, (_, kind) in nets.items() if kind == "int8"}
    rates = {name: 1 / b[0] for name, b in best.items()}
    fastest = max((name for name in nets if name != REFERENCE), key=rates.get)
    n = len(plain)
    extra = {"size": size, "tiles": [list(x.shape[-2:]) for x in plain], "threads": threads, "repeats": repeats,
             "seed": seed, "clock": "process CPU time", "networks": list(nets), "fastest": fastest,
             "frames_per_s": rates, "wall_frames_per_s": {name: 1 / b[1] for name, b in best.items()},
             "max_abs_diff": diffs, "weights": None if weights is None else str(weights),
             "reference_weights": str(DEFAULT_WEIGHTS if reference_weights is None else reference_weights),
             "load_average": load_average()}
    return BenchResult(f"detector network, {size}x{size} frame ({n} tile{'s' * (n > 1)}), "
                       f"{threads} thread{'s' * (threads > 1)}", rates[fastest], REFERENCE, rates[REFERENCE],
                       "frames", extra)


def format_report(result: BenchResult) -> str:
    """The workload, every network's frames/s (CPU time and wall clock) and ratio to the reference, and the int8
    networks' largest differences from their float ones."""
    e = result.extra
    rates, wall = e["frames_per_s"], e["wall_frames_per_s"]
    rows = [[name, f"{rates[name]:.2f}", f"{wall[name]:.2f}", f"{rates[name] / rates[REFERENCE]:.2f}x"]
            for name in e["networks"]]
    lines = [f"workload: {result.workload}",
             format_table(["network", "frames/s (CPU time)", "frames/s (wall)", "ratio (CPU time)"], rows)]
    for name, d in e["max_abs_diff"].items():
        lines.append(f"largest difference {name} - float: heatmap score {d['heatmap_score']:.3f}; where the float "
                     f"score reaches the threshold: offset {d['offset_cells_at_peaks']:.3f} cells, velocity "
                     f"{d['velocity_px_at_peaks']:.2f} px/frame")
    return "\n".join(lines)
