"""``torchtrack bench scale --frame-sizes``: the video pipeline as the frames grow from 512² to 4096² px.

The workload: for each frame side ``S``, ``n_S`` synthetic sequences of ``S × S`` px
(:func:`torchtrack.sim.video.write_sequence`, the generator's defaults, which keep the scene's density above
512²), each of the same number of frames at every size (so that the start-up of tracks weighs the same),
seeded by the held-out test seeds of the detector (:func:`torchtrack.detector.dataset.split_seed`, split
``test``, indices ``1 … n_S``). Fewer sequences for larger frames (:func:`default_sequences`: the same
pixels per size as one sequence of the largest size, at most :data:`MAX_SEQUENCES`) keep a run within minutes.

Each size's sequences are written as PNG folders and run through the pipeline as ``torchtrack track
--sequences DIR --no-video`` runs them (:func:`torchtrack.pipeline.sequences.run_sequences`: registration,
the detector in tiles, the enhanced GM-PHD; the embedded settings; the detector loaded once, outside the
timing, after an untimed warm-up sequence). Per size: megapixels per second end to end and per stage (wall
seconds of the pipeline's own clocks, frame decoding included; and end to end per CPU second of the process,
scoring included), the peak memory of the size's run (:class:`torchtrack.bench._memory.PeakMemory`: its
growth and the process's peak), MOTA pooled over the sequences (moving vehicles the targets, parked ones
don't-care), the detector's F1 on the same truth (its strong detections, ``detections.txt``, each matched
within the CLEAR-MOT threshold: ``2 TP / (2 TP + FP + FN)`` pooled) and the registration error against the
true camera (median of the sequences' medians, px).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from torchtrack.bench._memory import PeakMemory
from torchtrack.detector import load_detector
from torchtrack.detector.dataset import split_seed
from torchtrack.metrics.table import format_table
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.sequences import run_sequences
from torchtrack.sim.video import write_sequence
from torchtrack.sim.video_config import VideoConfig

FRAMES = 10
"""Frames per sequence, the same at every size."""

MAX_SEQUENCES = 32
"""The most sequences :func:`default_sequences` gives a size."""

WARMUP_FRAMES = 3
"""Frames of an untimed sequence at the smallest size run first (imports, caches, first-call costs)."""

STAGES = ("registration", "detection", "tracking", "io")
"""The pipeline's timed stages (``metrics.json``'s ``timings_s``; no ``render``: no video is written)."""


def default_sequences(sizes: Sequence[int]) -> list[int]:
    """Sequences per size of ``sizes``: as many as give the pixels of one sequence of the largest size,
    ``ceil((S_max / S)²)``, at most :data:`MAX_SEQUENCES` (512, 1024, 2048, 4096 → 32, 16, 4, 1)."""
    largest = max(sizes)
    return [min(MAX_SEQUENCES, math.ceil((largest / s) ** 2)) for s in sizes]


def sequence_seed(seed: int, index: int) -> int:
    """Generator seed of sequence ``index`` (from 1): the detector's held-out test seeds."""
    return split_seed(seed, "test", index)


@dataclass
class FrameSizeRow:
    """One frame size: ``sequences`` × ``frames`` frames of ``size × size`` px through the pipeline."""

    size: int
    sequences: int
    frames: int
    megapixels: float                     # pixels of every frame run, / 10⁶
    seconds: float                        # wall seconds of the runs (the pipeline's own end-to-end clock)
    cpu_seconds: float                    # process CPU seconds of the runs (every thread)
    mpx_per_s: float                      # end to end, wall
    mpx_per_cpu_s: float                  # end to end, per CPU second (steadier on a shared machine)
    stage_mpx_per_s: dict[str, float]     # per stage of STAGES: megapixels / that stage's wall seconds
    peak_memory_mb: float                 # growth over the memory held before the size's run (MiB)
    process_peak_mb: float                # the process's peak (CPU: resident set; CUDA: allocated) (MiB)
    mota: float
    detection_f1: float
    detection_precision: float
    detection_recall: float
    registration_error_px: float | None   # median of the sequences' median transfer errors
    registration_error_max_px: float | None
    moving_truth: int                     # truth lines scored (moving vehicles × frames)


def write_sequences(size: int, count: int, frames: int, seed: int, root: Path) -> Path:
    """``count`` sequences of ``frames`` frames of ``size × size`` px under ``root`` (one folder per seed)."""
    root.mkdir(parents=True, exist_ok=True)
    for index in range(1, count + 1):
        s = sequence_seed(seed, index)
        write_sequence(VideoConfig(height=size, width=size, frames=frames), torch.Generator().manual_seed(s),
                       root / f"seed{s}")
    return root


def run_size(size: int, count: int, frames: int, seed: int, work: Path, config: PipelineConfig,
             detector) -> FrameSizeRow:
    """The row of one size: sequences written under ``work/<size>/sequences`` (untimed), the pipeline's
    outputs under ``work/<size>/run`` (:func:`~torchtrack.pipeline.sequences.run_sequences`)."""
    sequences = write_sequences(size, count, frames, seed, work / str(size) / "sequences")
    c0 = time.process_time()
    with PeakMemory(torch.device(config.device)) as memory:
        summary = run_sequences(sequences, work / str(size) / "run", config, detector, progress=False)
    cpu = time.process_time() - c0
    runs = list(summary["sequences"].values())
    n_frames = sum(m["frames"] for m in runs)
    mpx = n_frames * size * size / 1e6
    seconds = sum(m["timings_s"]["total"] for m in runs)
    stage = {k: mpx / t for k in STAGES if (t := sum(m["timings_s"].get(k, 0.0) for m in runs)) > 0}
    tp, fp, fn = (sum(m["detector"][k] for m in runs) for k in ("TP", "FP", "FN"))
    aggregate = summary["aggregate"]
    reg = summary.get("registration_error_px", {})
    return FrameSizeRow(size, count, frames, mpx, seconds, cpu, mpx / seconds, mpx / cpu, stage, memory.mb,
                        memory.peak_mb, float(aggregate["MOTA"]), f1(tp, fp, fn), share(tp, fp),
                        share(tp, fn), reg.get("median_of_sequence_medians"), reg.get("max_of_sequence_medians"),
                        int(aggregate["GT"]))


def f1(tp: int, fp: int, fn: int) -> float:
    """``2 TP / (2 TP + FP + FN)`` (0 where there is nothing to find or found)."""
    return 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 0.0


def share(tp: int, other: int) -> float:
    """``TP / (TP + other)``: the precision with ``other`` the false positives, the recall with the misses (0
    where the denominator is)."""
    return tp / (tp + other) if tp + other else 0.0


def pipeline_config(device: str = "cpu", threads: int = 1) -> PipelineConfig:
    """The embedded pipeline settings (enhanced GM-PHD) without the video, on ``device``."""
    return PipelineConfig(video=False, device=device, threads=threads)


def measure(sizes: Sequence[int], work: Path, frames: int = FRAMES, sequences: Sequence[int] | None = None,
            device: str = "cpu", threads: int = 1, seed: int = 0,
            progress: Callable[[FrameSizeRow], None] | None = None) -> list[FrameSizeRow]:
    """One :class:`FrameSizeRow` per size of ``sizes`` (ascending), the files under ``work``; ``sequences``
    per size (default :func:`default_sequences`); ``progress(row)`` after each size."""
    counts = list(sequences) if sequences is not None else default_sequences(sizes)
    config = pipeline_config(device, threads)
    detector = load_detector(config.detector_weights, config.detector_tile, config.detector_backend)
    detector.net.to(config.device)
    run_size(min(sizes), 1, WARMUP_FRAMES, seed, work / "warmup", config, detector)
    rows = []
    for size, count in sorted(zip(sizes, counts)):
        rows.append(run_size(size, count, frames, seed, work, config, detector))
        if progress is not None:
            progress(rows[-1])
    return rows


def format_row(r: FrameSizeRow) -> str:
    """One progress line."""
    return (f"{r.size}²: {r.sequences} × {r.frames} frames, {r.mpx_per_s:.2f} Mpx/s end to end "
            f"({r.mpx_per_cpu_s:.2f} per CPU-s), MOTA {100 * r.mota:.1f} %, detection F1 {r.detection_f1:.3f}, "
            f"peak +{r.peak_memory_mb:.0f} MB (process {r.process_peak_mb:.0f} MB)")


def format_report(rows: Sequence[FrameSizeRow], workload_text: str) -> str:
    """The workload line and the table of every size."""
    def num(x, fmt):
        return "—" if x is None else format(x, fmt)
    table = [[f"{r.size}²", f"{r.sequences}×{r.frames}", num(r.mpx_per_s, ".2f"), num(r.mpx_per_cpu_s, ".2f"),
              *(num(r.stage_mpx_per_s.get(k), ".1f") for k in STAGES), num(r.mota, ".1%"),
              num(r.detection_f1, ".3f"), num(r.registration_error_px, ".3f"), num(r.peak_memory_mb, ".0f"),
              num(r.process_peak_mb, ".0f")] for r in rows]
    return "\n".join([f"workload: {workload_text}",
                      format_table(["frame", "seq×frames", "Mpx/s", "Mpx/CPU-s", *(f"{k} Mpx/s" for k in STAGES),
                                    "MOTA", "det F1", "reg err px", "peak +MB", "process MB"], table)])


def workload(frames: int, device: str, threads: int) -> str:
    return (f"synthetic video (generator defaults, held-out seeds), {frames} frames per sequence at every size, "
            f"pipeline defaults (enhanced GM-PHD, detector tiles), no video, {device}, {threads} torch thread(s)")


def payload(rows: Sequence[FrameSizeRow], workload_text: str) -> dict:
    """The JSON: the design's bench keys (``ours_per_s``: megapixels/s end to end at the largest size,
    ``reference_per_s``: at the smallest, ``ratio`` their ratio, 1 when the rate per pixel holds) and ``rows``,
    one per size."""
    first, last = (rows[0], rows[-1]) if rows else (None, None)
    return {"workload": workload_text, "ours_per_s": last.mpx_per_s if last else None,
            "reference": f"{first.size}x{first.size}" if first else None,
            "reference_per_s": first.mpx_per_s if first else None,
            "ratio": last.mpx_per_s / first.mpx_per_s if first else None, "unit": "megapixels",
            "rows": [asdict(r) for r in rows]}


def plot(rows: Sequence[FrameSizeRow], path: str | Path, title: str) -> None:
    """Megapixels/s (end to end and per stage), peak memory, and MOTA and detection F1 against the frame
    side (log x), as a PNG (written whole)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchtrack.io.outputs import save_figure

    sizes = [r.size for r in rows]
    fig, (ax_rate, ax_mem, ax_score) = plt.subplots(1, 3, figsize=(14, 4.2))
    ax_rate.plot(sizes, [r.mpx_per_s for r in rows], "o-", lw=2, label="end to end")
    ax_rate.plot(sizes, [r.mpx_per_cpu_s for r in rows], "o--", label="end to end, per CPU-s")
    for k in STAGES:
        ax_rate.plot(sizes, [r.stage_mpx_per_s.get(k, math.nan) for r in rows], ".:", label=k)
    ax_rate.set(yscale="log", ylabel="megapixels/s")
    ax_mem.plot(sizes, [r.process_peak_mb for r in rows], "o-", label="process peak")
    ax_mem.plot(sizes, [r.peak_memory_mb for r in rows], "o--", label="growth during the run")
    ax_mem.set(ylabel="peak memory (MiB)")
    ax_score.plot(sizes, [r.mota for r in rows], "o-", label="MOTA (moving vehicles)")
    ax_score.plot(sizes, [r.detection_f1 for r in rows], "s-", label="detection F1")
    ax_score.set(ylabel="score")
    for ax in (ax_rate, ax_mem, ax_score):
        ax.set_xscale("log", base=2)
        ax.set_xticks(sizes, [f"{s}²" for s in sizes])
        ax.set_xlabel("frame (px)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=8)
    save_figure(fig, path, dpi=110)


def print_progress(row: FrameSizeRow) -> None:
    print(format_row(row), file=sys.stderr, flush=True)
