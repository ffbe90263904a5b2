"""``torchtrack bench scale``: the trackers as the number of vehicles per frame grows at constant density.

The workload: ``N`` vehicles, one per 60 × 60 px, on a square of side ``60 √N`` px, each moving on
a straight line at 2.5–3.5 px/frame with a uniformly random heading; each frame a vehicle is detected with
probability ``p_D = 0.9`` at its position plus ``N(0, σ² I)``, ``σ = 1`` px, with the detector's velocity plus
``N(0, 1)`` px/frame; ``N / 4`` clutter detections per frame, uniform over the square, with velocities uniform
over ±10 px/frame. Every tracker runs at its built-in defaults (PMB's ``region`` and ``clutter_rate`` set to the
square and the clutter count, which it needs to know) on the same detections.

Per (tracker, N): frames/s of the tracker's steps alone (simulation and scoring excluded; wall time, and per
CPU second of the process, which a shared machine's load does not change), CLEAR-MOT MOTA at
10 px, the CPU cost per vehicle-frame relative to the smallest ``N`` of that tracker, the component cap hits
where the tracker counts them, and the peak memory of the run (CUDA: ``torch.cuda.max_memory_allocated``;
CPU: the growth of the peak resident set, reset before each run where Linux allows it; memory the process
kept from an earlier run is reused uncounted, so small CPU figures are lower bounds). A run whose tracker
time passes ``max_seconds`` stops there (its frames/s from the frames done, no MOTA) and the larger ``N`` of
that tracker are skipped; both are recorded.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from torchtrack.bench._memory import PeakMemory
from torchtrack.filters.trackers.protocol import make_tracker, tracker_names
from torchtrack.io.mot import MOTData
from torchtrack.metrics.clear_mot import clear_mot
from torchtrack.metrics.table import format_table
from torchtrack.threads import torch_threads

CELL = 60.0            # px² per vehicle: one vehicle per CELL × CELL
SPEED = (2.5, 3.5)     # px/frame
P_DETECTION = 0.9
SIGMA = 1.0            # position noise, px
VELOCITY_SIGMA = 1.0   # detector velocity noise, px/frame
CLUTTER_PER_VEHICLE = 0.25
CLUTTER_SPEED = 10.0   # clutter velocities uniform over ±this, px/frame
THRESHOLD = 10.0       # CLEAR-MOT centre distance, px


@dataclass(frozen=True)
class Scene:
    """A simulated sequence: ``side`` px square, truth ``gt`` and per frame ``(frame, positions (K, 2),
    velocities (K, 2))`` float64 detections (frames from 1)."""

    vehicles: int
    side: float
    gt: MOTData
    detections: list[tuple[int, torch.Tensor, torch.Tensor]]

    @property
    def clutter_per_frame(self) -> int:
        return round(CLUTTER_PER_VEHICLE * self.vehicles)


def simulate(vehicles: int, frames: int, seed: int) -> Scene:
    """The constant-density workload of the module docstring for ``vehicles`` over ``frames`` frames."""
    gen = torch.Generator().manual_seed(seed)
    f64 = {"dtype": torch.float64, "generator": gen}
    side = CELL * math.sqrt(vehicles)
    start = torch.rand(vehicles, 2, **f64) * side
    heading = torch.rand(vehicles, **f64) * 2 * math.pi
    speed = SPEED[0] + (SPEED[1] - SPEED[0]) * torch.rand(vehicles, **f64)
    vel = speed.unsqueeze(1) * torch.stack([heading.cos(), heading.sin()], 1)
    clutter = round(CLUTTER_PER_VEHICLE * vehicles)
    gt_frame, gt_id, gt_xy, dets = [], [], [], []
    for t in range(frames):
        pos = start + t * vel
        gt_frame.append(np.full(vehicles, t + 1))
        gt_id.append(np.arange(1, vehicles + 1))
        gt_xy.append(pos.numpy())
        seen = torch.rand(vehicles, generator=gen) < P_DETECTION
        z = pos[seen] + SIGMA * torch.randn(int(seen.sum()), 2, **f64)
        v = vel[seen] + VELOCITY_SIGMA * torch.randn(int(seen.sum()), 2, **f64)
        zc = torch.rand(clutter, 2, **f64) * side
        vc = (2 * torch.rand(clutter, 2, **f64) - 1) * CLUTTER_SPEED
        order = torch.randperm(z.shape[0] + clutter, generator=gen)
        dets.append((t + 1, torch.cat([z, zc])[order], torch.cat([v, vc])[order]))
    return Scene(vehicles, side, points(np.concatenate(gt_frame), np.concatenate(gt_id), np.concatenate(gt_xy)),
                 dets)


def points(frame: np.ndarray, ids: np.ndarray, xy: np.ndarray) -> MOTData:
    """Point objects ``xy (K, 2)`` as MOTChallenge data (zero-size boxes: the centre is the point)."""
    zeros = np.zeros(frame.shape[0])
    return MOTData(frame.astype(np.int64), ids.astype(np.int64), xy[:, 0].astype(np.float64),
                   xy[:, 1].astype(np.float64), zeros, zeros.copy(), np.ones(frame.shape[0]))


def tracker_options(name: str, scene: Scene) -> dict | None:
    """The built-in defaults, except what PMB must know of the scene (its region and clutter count)."""
    if name == "pmb":
        return {"region": (0.0, 0.0, scene.side, scene.side), "clutter_rate": float(scene.clutter_per_frame)}
    return None


@dataclass
class ScaleRow:
    """One (tracker, N) run; ``status`` ``ok``, ``over time limit`` (stopped after ``frames_run`` frames, no
    MOTA) or ``skipped`` (a smaller N of the tracker went over the limit; nothing measured)."""

    tracker: str
    vehicles: int
    status: str
    frames_run: int = 0
    seconds: float | None = None
    fps: float | None = None
    cpu_fps: float | None = None         # frames per CPU second of the process (steady under a shared machine's load)
    mota: float | None = None
    vehicle_frames_per_s: float | None = None
    cost_ratio: float | None = None      # CPU cost per vehicle-frame / the same at the tracker's smallest N
    cap_hits: int | None = None
    peak_memory_mb: float | None = None
    side_px: float | None = None
    detections_per_frame: float | None = None


@contextmanager
def _quiet_filters() -> Iterator[None]:
    """The filters' cap warnings (one per frame once a cap binds) are not printed during a run: the GM-PHD
    counts them in ``cap_hits``; PMB logs its first one only."""
    logger = logging.getLogger("torchtrack.filters")
    sink = logging.NullHandler()          # a logger without any handler would print through logging.lastResort
    propagate, logger.propagate = logger.propagate, False
    logger.addHandler(sink)
    try:
        yield
    finally:
        logger.removeHandler(sink)
        logger.propagate = propagate


WARMUP_FRAMES = 3
"""Untimed frames each tracker runs first (imports, caches, first-call costs), then it is reset."""


def run_one(name: str, scene: Scene, device: torch.device, max_seconds: float,
            options: Mapping | None = None) -> ScaleRow:
    """Tracker ``name`` over ``scene`` on ``device`` (``options``: its keys to change, over
    :func:`tracker_options`), after a warm-up on its first frames; stops once its step time passes
    ``max_seconds``."""
    tracker = make_tracker(name, {**(tracker_options(name, scene) or {}), **(options or {})})
    dets = [(f, z.to(device), v.to(device)) for f, z, v in scene.detections]
    with _quiet_filters():
        for frame, z, v in dets[:WARMUP_FRAMES]:
            tracker.step(frame, z, v)
    tracker.reset()
    hits_before = getattr(tracker, "cap_hits", None)        # a GM-PHD's count runs on over resets
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    out_frame, out_id, out_xy = [], [], []
    elapsed, cpu, done = 0.0, 0.0, 0
    with PeakMemory(device) as memory, _quiet_filters():
        for frame, z, v in dets:
            sync()
            t0, c0 = time.perf_counter(), time.process_time()
            ids, pos = tracker.step(frame, z, v)
            sync()
            elapsed += time.perf_counter() - t0
            cpu += time.process_time() - c0
            done += 1
            out_frame.append(np.full(ids.shape[0], frame))
            out_id.append(ids.cpu().numpy())
            out_xy.append(pos.detach().cpu().double().numpy().reshape(-1, 2))
            if elapsed > max_seconds:
                break
    complete = done == len(dets)
    row = ScaleRow(name, scene.vehicles, "ok" if complete else "over time limit", done, elapsed,
                   done / elapsed if elapsed > 0 else float("inf"), done / cpu if cpu > 0 else float("inf"),
                   cap_hits=None if hits_before is None else tracker.cap_hits - hits_before,
                   peak_memory_mb=memory.mb, side_px=scene.side,
                   detections_per_frame=float(np.mean([z.shape[0] for _, z, _ in dets])))
    row.vehicle_frames_per_s = row.fps * scene.vehicles
    if complete:
        pred = points(np.concatenate(out_frame), np.concatenate(out_id), np.concatenate(out_xy))
        row.mota = float(clear_mot(scene.gt, pred, threshold=THRESHOLD)["MOTA"])
    return row


def measure(vehicles: Sequence[int] = (100, 300, 1000, 3000, 10000), trackers: Sequence[str] | None = None,
            frames: int = 40, device: str = "cpu", max_seconds: float = 120.0, threads: int = 1, seed: int = 0,
            progress: Callable[[ScaleRow], None] | None = None) -> list[ScaleRow]:
    """One :class:`ScaleRow` per (tracker, N) of ``trackers`` (default: every registered one) and ``vehicles``
    (ascending), each tracker on the same seeded scene per N; ``progress(row)`` after each row."""
    names = list(trackers) if trackers else tracker_names()
    sizes = sorted(set(vehicles))
    dev = torch.device(device)
    rows: dict[tuple[str, int], ScaleRow] = {}
    over: set[str] = set()
    with torch_threads(threads):
        for n in sizes:
            scene = None
            for name in names:
                if name in over:
                    row = ScaleRow(name, n, "skipped")
                else:
                    scene = scene or simulate(n, frames, seed)
                    row = run_one(name, scene, dev, max_seconds)
                    if row.seconds > max_seconds:
                        over.add(name)
                rows[name, n] = row
                if progress is not None:
                    progress(row)
    out = [rows[name, n] for name in names for n in sizes]
    for name in names:
        base = next((r for r in out if r.tracker == name and r.cpu_fps), None)
        for r in out:
            if r.tracker == name and r.cpu_fps and base is not None:
                r.cost_ratio = (base.cpu_fps * base.vehicles) / (r.cpu_fps * r.vehicles)
    return out


def format_row(r: ScaleRow) -> str:
    """One progress line."""
    if r.status == "skipped":
        return f"{r.tracker:>15} N={r.vehicles:<6} skipped (a smaller N went over the time limit)"
    mota = "—" if r.mota is None else f"{100 * r.mota:.1f} %"
    return (f"{r.tracker:>15} N={r.vehicles:<6} {r.status}: {r.fps:8.2f} frames/s over {r.frames_run} frames, "
            f"MOTA {mota}, cap hits {r.cap_hits}, peak {r.peak_memory_mb:.0f} MB")


def format_report(rows: Sequence[ScaleRow], workload: str) -> str:
    """The workload line and the table of every row."""
    def num(x, fmt):
        return "—" if x is None else format(x, fmt)
    table = [[r.tracker, r.vehicles, r.status, num(r.fps, ".2f"), num(r.cpu_fps, ".2f"), num(r.mota, ".1%"),
              num(r.cost_ratio, ".2f"), num(r.cap_hits, "d"), num(r.peak_memory_mb, ".0f")] for r in rows]
    return "\n".join([f"workload: {workload}",
                      format_table(["tracker", "N", "status", "frames/s", "frames/CPU-s", "MOTA", "cost/veh-frame ×",
                                    "cap hits", "peak MB"], table)])


def workload(frames: int, device: str, threads: int) -> str:
    return (f"constant density (1 vehicle per {CELL:.0f}x{CELL:.0f} px, {SPEED[0]}-{SPEED[1]} px/frame, p_D "
            f"{P_DETECTION}, sigma {SIGMA} px, clutter N/4, detector velocities), {frames} frames, {device}, "
            f"{threads} thread(s)")


def payload(rows: Sequence[ScaleRow], workload_text: str) -> dict:
    """The JSON: the design's bench keys for the first tracker (``ours_per_s``: vehicle-frames/s at its largest
    measured N, ``reference_per_s``: at its smallest; ``ratio`` their ratio, 1 when the cost per vehicle-frame
    is flat) and ``rows``, one per (tracker, N)."""
    first = [r for r in rows if r.tracker == rows[0].tracker and r.vehicle_frames_per_s] if rows else []
    ours = first[-1].vehicle_frames_per_s if first else None
    ref = first[0].vehicle_frames_per_s if first else None
    return {"workload": workload_text, "ours_per_s": ours,
            "reference": f"{first[0].tracker} at N={first[0].vehicles}" if first else None,
            "reference_per_s": ref, "ratio": ours / ref if first else None, "unit": "vehicle-frames",
            "rows": [asdict(r) for r in rows]}


def plot(rows: Sequence[ScaleRow], path: str | Path, title: str) -> None:
    """Frames/s and MOTA against N (log x), one line per tracker, as a PNG (written whole)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchtrack.io.outputs import save_figure

    fig, (ax_fps, ax_mota) = plt.subplots(1, 2, figsize=(11, 4.2))
    for name in dict.fromkeys(r.tracker for r in rows):
        mine = [r for r in rows if r.tracker == name and r.fps is not None]
        ax_fps.plot([r.vehicles for r in mine], [r.fps for r in mine], "o-", label=name)
        scored = [r for r in mine if r.mota is not None]
        ax_mota.plot([r.vehicles for r in scored], [r.mota for r in scored], "o-", label=name)
    ax_fps.set(xscale="log", yscale="log", xlabel="vehicles per frame N", ylabel="frames/s (tracker only)")
    ax_mota.set(xscale="log", xlabel="vehicles per frame N", ylabel="MOTA (10 px)")
    for ax in (ax_fps, ax_mota):
        ax.grid(True, which="both", alpha=0.3)
    ax_mota.legend()
    fig.suptitle(title, fontsize=8)
    save_figure(fig, path, dpi=110)


def print_progress(row: ScaleRow) -> None:
    print(format_row(row), file=sys.stderr, flush=True)
