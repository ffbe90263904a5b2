"""``torchtrack bench detector``: the detector's network in int8 against the float network, the same weights.

Per frame size ``S``: a synthetic ``S × S`` sequence of two frames (the shipped generator, seed ``--seed``) is
streamed through the float detector and the network inputs of its second frame are kept — the tiles that
``Detector.detect`` runs (one window up to 1280 px, else 1024 px cores with a 128 px halo: four 1152² windows
at 2048²). The float network (the reference, as ``Detector`` ran it before int8: channels-last float32) and the
int8 network (:mod:`torchtrack.detector.quantized`, the checkpoint's calibration) then run those tiles in
alternation, ``repeats`` times each; the fastest pass of each is kept, in process CPU time (what an idle core
gives; the wall time of a shared machine counts the waits) and in wall time. Frames/s is one frame's tiles per
second. The maps' agreement on these inputs is reported beside: the largest difference of the heatmap scores
(sigmoid) over all cells, and of the offsets (cells) and velocities (px/frame) over the cells whose float score
reaches the decoding threshold (elsewhere they are never read).
"""

from __future__ import annotations

import torch

from torchtrack.bench._timing import CLOCKS, BenchResult, load_average
from torchtrack.detector.checkpoint import load_checkpoint
from torchtrack.detector.inference import DEFAULT_WEIGHTS, detector_from_checkpoint
from torchtrack.detector.quantized import calibration_inputs
from torchtrack.metrics.table import format_table
from torchtrack.sim.video_config import from_dict
from torchtrack.threads import torch_threads

SIZES = (512, 2048)


def _pass(net, tiles: list[torch.Tensor]) -> tuple[float, float]:
    """(CPU seconds, wall seconds) of ``net`` over the tiles."""
    c0, t0 = CLOCKS[1](), CLOCKS[0]()
    for x in tiles:
        net(x)
    return CLOCKS[1]() - c0, CLOCKS[0]() - t0


def measure(size: int, repeats: int = 5, seed: int = 0, weights=None, threads: int = 1) -> BenchResult:
    """The float and int8 networks' frames/s on the tiles of one ``size × size`` frame (module docstring)."""
    data = load_checkpoint(DEFAULT_WEIGHTS if weights is None else weights)
    with torch_threads(threads), torch.inference_mode():
        det = detector_from_checkpoint(data, backend="int8")
        fast = det._int8[0]
        det._int8 = None                                   # the float network gives the inputs
        video = from_dict(dict(det.config.data.video)).replace(width=size, height=size, frames=2)
        inputs = calibration_inputs(det, video, [seed])
        # each network's tiles as Detector.tiles gives them: channels-last to the float one, contiguous to int8
        tiles = {"int8": [x.contiguous() for x in inputs[len(inputs) // 2:]]}
        tiles["float"] = [x.contiguous(memory_format=torch.channels_last) for x in tiles["int8"]]
        nets = {"float": det.net, "int8": fast}
        ref, out = ([torch.cat(nets[k](x), 1) for x in tiles[k]] for k in ("float", "int8"))
        best = {"float": [float("inf")] * 2, "int8": [float("inf")] * 2}
        for k in nets:
            _pass(nets[k], tiles[k])                        # warm-up
        for _ in range(repeats):
            for k in nets:
                best[k] = [min(a, b) for a, b in zip(best[k], _pass(nets[k], tiles[k]))]
    threshold = det.config.decode.threshold
    score = max((a[:, :1].sigmoid() - b[:, :1].sigmoid()).abs().max().item() for a, b in zip(ref, out))
    peaks = [(a[:, :1].sigmoid() >= threshold).expand(-1, 2, -1, -1) for a in ref]    # where the float detects
    diff = [score] + [max(float((a[:, sl] - b[:, sl]).abs()[m].max()) if m.any() else 0.0
                          for a, b, m in zip(ref, out, peaks)) for sl in (slice(1, 3), slice(3, 5))]
    extra = {"size": size, "tiles": [list(x.shape[-2:]) for x in tiles["int8"]], "threads": threads, "repeats": repeats,
             "seed": seed, "clock": "process CPU time",
             "wall_frames_per_s": {k: 1 / v[1] for k, v in best.items()},
             "max_abs_diff": dict(zip(("heatmap_score", "offset_cells_at_peaks", "velocity_px_at_peaks"), diff)),
             "load_average": load_average()}
    n = len(tiles["int8"])
    return BenchResult(f"detector network, {size}x{size} frame ({n} tile{'s' * (n > 1)}), "
                       f"{threads} thread{'s' * (threads > 1)}", 1 / best["int8"][0], "float network",
                       1 / best["float"][0], "frames", extra)


def format_report(result: BenchResult) -> str:
    """The workload, both networks' frames/s (CPU and wall clock), the ratios and the maps' largest differences."""
    e = result.extra
    d, wall = e["max_abs_diff"], e["wall_frames_per_s"]
    rows = [["int8 network", f"{result.ours_per_s:.2f}", f"{wall['int8']:.2f}"],
            [result.reference, f"{result.reference_per_s:.2f}", f"{wall['float']:.2f}"]]
    return "\n".join([f"workload: {result.workload}",
                      format_table(["implementation", "frames/s (CPU time)", "frames/s (wall)"], rows),
                      f"ratio: {result.ratio:.2f}x (wall: {wall['int8'] / wall['float']:.2f}x)",
                      f"largest difference int8 - float: heatmap score {d['heatmap_score']:.3f}; where the float "
                      f"score reaches the threshold: offset {d['offset_cells_at_peaks']:.3f} cells, velocity "
                      f"{d['velocity_px_at_peaks']:.2f} px/frame"])
