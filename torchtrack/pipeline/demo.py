"""``torchtrack demo``: the paper's Table 1 on a synthetic sequence, end to end, in one command.

1. generate the embedded default synthetic sequence (:class:`~torchtrack.sim.video.VideoConfig`
   defaults, 512 × 512), seeded in the detector's held-out test split
   (``detector.dataset.split_seed(seed, "test", 0)``), into ``out/sequence/`` (frames, ``gt.txt``,
   ``velocity.txt``, ``camera.json``);
2. run the pipeline once with the enhanced GM-PHD (registration, the shipped detector, tracking,
   ``tracks.txt``, ``annotated.mp4``), keeping each frame's detections;
3. run every other tracker on **the same detections** (the detector runs once) and score them all;
4. print the CLEAR-MOT table in the layout of the paper's Table 1 (GT, MT/PT/ML %, FP, FN, IDS,
   MOTA %, HOTA % and IDF1 % added, MOTP px, tracker FPS), and write ``metrics.json`` and the plots
   ``tracks_first_frame.png`` and ``scores.png``.

Scoring follows the paper: the targets are the moving vehicles (``truth="moving"``,
:func:`torchtrack.io.moving.moving_mask`: the generator's ``velocity.txt`` flag, i.e. vehicles driving on a
lane; ``torchtrack eval --moving`` on ``sequence/gt.txt`` gives the same scores), parked vehicles are
don't-care (a track on one is neither a hit nor a false positive; ``clear_mot(..., ignore=...)``), 10 px
centre distance.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from torchtrack.detector.dataset import split_seed
from torchtrack.filters.trackers.protocol import make_tracker, tracker_names
from torchtrack.geometry import apply_homography
from torchtrack.io.frames import FolderSource
from torchtrack.io.mot import MOTData, read_mot
from torchtrack.io.moving import flags_beside, moving_mask
from torchtrack.io.outputs import write_json
from torchtrack.metrics.table import format_table1, protocol, score
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.plots import plot_scores, plot_tracks
from torchtrack.pipeline.replay import run_tracker
from torchtrack.pipeline.track_video import track_video
from torchtrack.sim.video import VideoConfig, read_camera, write_sequence


def _paths(data: MOTData, to_first: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Each identity's positions in first-frame coordinates; ``to_first`` frame → (3, 3) homography."""
    paths: dict[int, list] = {}
    centers = data.centers()
    for f, idx in zip(data.frames(), data.split()):
        for i, p in zip(data.id[idx].tolist(), apply_homography(centers[idx], to_first[int(f)])):
            paths.setdefault(i, []).append(p)
    return {i: np.array(p) for i, p in paths.items() if len(p) > 1}


def _clear_sequence(folder: Path) -> None:
    """Remove the files a previous demo generated in ``folder`` (a longer run would leave extra frames)."""
    for f in (*folder.glob("frames/*.png"), *(folder / n for n in ("gt.txt", "velocity.txt", "camera.json"))):
        f.unlink(missing_ok=True)


def run_demo(out: str | Path = "out/demo", seed: int = 0, frames: int | None = None, truth: str = "moving",
             video_config: VideoConfig | None = None, config: PipelineConfig | None = None,
             progress: bool = True) -> dict:
    """Run the demo (module docstring); returns the ``metrics.json`` payload (its ``files``: the names of
    the files written, relative to ``out``, so that they stay true when the folder is moved into place)."""
    out = Path(out)
    t_start = time.perf_counter()
    vcfg = video_config or VideoConfig()
    if frames is not None:
        vcfg = vcfg.replace(frames=frames)
    _clear_sequence(out / "sequence")
    # A sequence of the detector's held-out test split: never seen in training or validation.
    gen_seed = split_seed(seed, "test", 0)
    seq = write_sequence(vcfg, torch.Generator().manual_seed(gen_seed), out / "sequence", progress=progress)
    t_generated = time.perf_counter()
    gt = read_mot(seq / "gt.txt")
    ignore = ~moving_mask(gt, flags_beside(seq / "gt.txt")) if truth == "moving" else None
    cfg = config or PipelineConfig()
    cfg = cfg.replace(snapshots=tuple(sorted({*cfg.snapshots, min(vcfg.frames, 20)})))
    camera = read_camera(seq / "camera.json")
    result = track_video(FolderSource(seq / "frames"), out, cfg, gt=gt, gt_path=str(seq / "gt.txt"), ignore=ignore,
                         camera=camera, keep_detections=True, progress=progress)
    metrics = result.metrics
    metrics["source"] = "sequence/frames"        # relative to out, as ``files``: out is moved into place at the end
    scores = {cfg.tracker: {**metrics["clear_mot"], "FPS": metrics["fps"].get("tracking_only", float("inf"))}}
    for name in [n for n in tracker_names() if n != cfg.tracker]:
        run = run_tracker(make_tracker(name, cfg.options_for(name)), cfg, result.detections,
                          out / "trackers" / f"{name}.txt")
        scores[name] = {**score(gt, run.tracks, cfg.threshold, ignore), "FPS": run.fps}
    homographies = {d.index: d.homography for d in result.detections}
    first = next(iter(FolderSource(seq / "frames"))).image
    true_to_first = {k + 1: camera[0] @ np.linalg.inv(h) for k, h in enumerate(camera)}
    plots = {
        "tracks": plot_tracks(first, _paths(result.tracks, homographies),
                              out / "tracks_first_frame.png",
                              f"{cfg.tracker} tracks over frame 1 (white: truth), {vcfg.frames} frames",
                              _paths(gt if ignore is None else gt.select(~ignore), true_to_first)),
        "scores": plot_scores(scores, out / "scores.png"),
    }
    metrics.update({
        "demo": {"seed": seed, "generator_seed": gen_seed, "frames": vcfg.frames,
                 "size": [vcfg.height, vcfg.width], "truth": truth, "threshold": cfg.threshold,
                 "generate_s": t_generated - t_start, "total_s": time.perf_counter() - t_start},
        "trackers": scores,
        "files": {k: str(Path(v).relative_to(out)) for k, v in {**result.files, **plots}.items()},
    })
    write_json(out / "metrics.json", metrics)
    return metrics


def format_demo(metrics: dict) -> str:
    """The Table 1 text plus the end-to-end line."""
    demo = metrics["demo"]
    table = format_table1(metrics["trackers"], protocol(demo["truth"] == "moving", demo["threshold"]))
    fps = metrics["fps"]
    det = metrics.get("detector", {})
    lines = [
        f"synthetic sequence: {metrics['demo']['frames']} frames of {metrics['demo']['size'][1]}x"
        f"{metrics['demo']['size'][0]}, seed {metrics['demo']['seed']}, truth: {metrics['demo']['truth']} vehicles",
        table,
        f"FPS: the tracker alone on the shared detections. End to end ({metrics['tracker']}: registration, "
        f"detection, tracking, I/O, rendering): {fps['end_to_end']:.1f} frames/s.",
    ]
    if det:
        lines.append(f"detector: precision {det['precision']:.3f}, recall {det['recall']:.3f}, "
                     f"MOTP {det['MOTP']:.2f} px")
    if "registration_error_px" in metrics:
        lines.append(f"registration error vs true camera motion: median "
                     f"{metrics['registration_error_px']['median']:.3f} px")
    return "\n".join(lines)
