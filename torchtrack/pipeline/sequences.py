"""Many sequences: find them in a folder, run the pipeline on each, aggregate the metrics — on one
process or sharded over the ranks of ``torchrun`` (``torch.distributed``, gloo), rank 0 aggregating.

A sequence is a sub-folder ``S`` of the folder given, holding its frames as

* images directly in ``S``, or in ``S/frames/`` or ``S/img1/`` (the MOTChallenge layout), or
* one video file in ``S`` (``S/video.mp4`` as written by ``torchtrack simulate-video --format mp4``),

and optionally its truth ``S/gt.txt`` or ``S/gt/gt.txt``, and for synthetic sequences the true camera
motion ``S/camera.json`` (registration error is then measured) and ``S/velocity.txt`` (the simulator's flags of
the moving vehicles). By default only the moving vehicles are targets, the others don't-care, as ``eval --moving``
scores (:func:`torchtrack.io.moving.dont_care`: the flags where there are, else the paper's rule); ``score="all"``
makes every object a target. Sub-folders holding
none of these are skipped with a warning.

Aggregation is exact: the truth and tracks of all sequences are concatenated, with frame numbers and
identities offset so that sequences never mix, and CLEAR-MOT is computed once on the concatenation
(so MOTA, IDF1 and MT/PT/ML are those of the pooled events, as in MOTChallenge's "overall" row).
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Iterable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch.distributed as dist

from torchtrack.detector import load_detector
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.io.frames import IMAGE_SUFFIXES, VIDEO_SUFFIXES, FrameSource, open_frames
from torchtrack.io.mot import MOTData, concat_mot, read_mot
from torchtrack.io.moving import dont_care, flags_beside
from torchtrack.io.outputs import OutputFolder, write_json
from torchtrack.metrics.table import score as score_tracks
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.replay import run_tracker
from torchtrack.pipeline.track_video import track_video
from torchtrack.sim.video import read_camera


@dataclass
class Sequence:
    """One sequence: its ``name``, where its frames are, and its optional truth and camera files."""

    name: str
    frames: Path
    gt: Path | None = None
    camera: Path | None = None
    velocity: Path | None = None

    def source(self) -> FrameSource:
        return open_frames(self.frames)


def _has_images(folder: Path) -> bool:
    return folder.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in folder.iterdir())


def describe_sequence(folder: Path) -> Sequence | None:
    """The :class:`Sequence` stored in ``folder`` (layout in the module docstring), or None."""
    frames = next((c for c in (folder / "frames", folder / "img1", folder) if _has_images(c)), None)
    if frames is None:
        videos = sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
        if len(videos) > 1:
            raise TorchtrackError(f"{folder}: several videos ({', '.join(p.name for p in videos)}); "
                                  "keep one video per sequence folder")
        frames = videos[0] if videos else None
    if frames is None:
        return None
    gt = next((p for p in (folder / "gt.txt", folder / "gt" / "gt.txt") if p.is_file()), None)
    camera = folder / "camera.json"
    return Sequence(folder.name, frames, gt, camera if camera.is_file() else None,
                    flags_beside(gt) if gt is not None else None)


def find_sequences(root: str | Path) -> list[Sequence]:
    """Every sequence under ``root``, by name; errors name ``root`` when there is none."""
    root = Path(root)
    if not root.is_dir():
        raise TorchtrackError(f"{root}: no such folder (--sequences expects a folder of sequence folders)")
    found, skipped = [], []
    for sub in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        seq = describe_sequence(sub)
        (found if seq else skipped).append(seq or sub.name)
    if skipped:
        warnings.warn(f"{root}: skipping {len(skipped)} folder(s) without frames or video: "
                      f"{', '.join(skipped[:5])}", stacklevel=2)
    if not found:
        raise TorchtrackError(f"{root}: no sequence found (each sub-folder needs images, frames/, img1/ "
                              "or one video file)")
    return found


def run_sequence(seq: Sequence, out: Path, config: PipelineConfig, detector, progress: bool,
                 others: list[str] = (), score: str = "moving") -> dict:
    """Run the pipeline on one sequence, and the trackers ``others`` on the same detections (written to
    ``out/<sequence>/trackers/<name>.txt``), scored as ``score`` says (:func:`torchtrack.io.moving.dont_care`);
    returns what rank 0 needs to aggregate them."""
    gt = read_mot(seq.gt) if seq.gt else None
    ignore = dont_care(gt, score, seq.velocity) if gt is not None else None
    camera = read_camera(seq.camera) if seq.camera else None
    t0 = time.perf_counter()
    result = track_video(seq.source(), out / seq.name, config, detector=detector, gt=gt, gt_path=str(seq.gt),
                         ignore=ignore, camera=camera, keep_detections=bool(others), progress=progress)
    seconds = time.perf_counter() - t0
    tracks = {config.tracker: (result.tracks, result.metrics["timings_s"].get("tracking", 0.0))}
    for name in others:
        run = run_tracker(make_tracker(name, config.options_for(name)), config, result.detections,
                          out / seq.name / "trackers" / f"{name}.txt")
        tracks[name] = (run.tracks, run.seconds)
    return {"name": seq.name, "metrics": result.metrics, "seconds": seconds, "gt": gt, "ignore": ignore,
            "tracks": tracks}


def concatenate(parts: list[tuple[MOTData, MOTData]], offset_frames: bool = True) -> tuple[MOTData, MOTData]:
    """Pool ``(gt, tracks)`` pairs into one pair, offsetting identities (and, with ``offset_frames``, frame
    numbers) so that the parts never mix (lines keep their order, so per-line masks of the parts
    concatenate alongside)."""
    gts, preds = [], []
    frame_off = id_off = 0
    for gt, pred in parts:
        last = max(int(gt.frame.max()) if gt.size else 0, int(pred.frame.max()) if pred.size else 0)
        top = max(int(gt.id.max()) if gt.size else 0, int(pred.id.max()) if pred.size else 0)
        gts.append(gt._replace(frame=gt.frame + frame_off, id=gt.id + id_off))
        preds.append(pred._replace(frame=pred.frame + frame_off, id=pred.id + id_off))
        frame_off += (last + 1) if offset_frames else 0
        id_off += top + 1
    return concat_mot(gts), concat_mot(preds)


def _distributed() -> tuple[int, int]:
    """``(rank, world_size)``; initialises the gloo process group under ``torchrun``."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    if not dist.is_initialized():
        dist.init_process_group("gloo")
    return dist.get_rank(), dist.get_world_size()


@contextmanager
def shared_output(out: str | Path, command: str, force: bool = False,
                  inputs: Iterable[str | os.PathLike | None] = ()) -> Iterator[Path]:
    """The staging folder of the output folder ``out`` (:class:`~torchtrack.io.outputs.OutputFolder`) for
    every process of a run: one process alone, or every ``torchrun`` rank.

    Rank 0 checks and prepares the folder and tells the others (its refusal becomes every rank's error);
    then all ranks write into the same staging folder (``out`` must be on a file system they share) and,
    once every rank has left the block normally (a barrier), rank 0 commits the set. ``inputs``: the paths
    the run reads (refused inside ``out``).
    """
    rank, world = _distributed()
    folder = OutputFolder(out, command, force=force, commit=rank == 0, inputs=inputs)
    with ExitStack() as stack:
        refusal: list[str | None] = [None]
        if rank == 0:
            try:
                stack.enter_context(folder)
            except TorchtrackError as exc:
                refusal[0] = str(exc)
        if world > 1:
            dist.broadcast_object_list(refusal, src=0)
        if refusal[0] is not None:
            raise TorchtrackError(refusal[0])
        yield folder.staging
        if world > 1:
            dist.barrier()


def run_sequences(root: str | Path, out: str | Path, config: PipelineConfig, detector=None,
                  progress: bool = True, compare: list[str] = (), score: str = "moving") -> dict | None:
    """Evaluate every sequence of ``root`` and aggregate (module docstring), scored as ``score`` says (``moving``
    or ``all``); with ``compare``, those trackers also run on the same detections and ``summary["trackers"]``
    holds each one's pooled CLEAR-MOT and tracker-only frames per second.

    Under ``torchrun`` rank ``r`` of ``W`` takes sequences ``r, r + W, ...``; results are gathered on
    rank 0, which writes ``out/metrics.json`` and returns the summary; other ranks return None.
    """
    out = Path(out)
    sequences = find_sequences(root)
    rank, world = _distributed()
    if detector is None:
        detector = load_detector(config.detector_weights, config.detector_tile, config.detector_backend)
    others = [n for n in compare if n != config.tracker]
    mine = [run_sequence(s, out, config, detector, progress and rank == 0, others, score)
            for s in sequences[rank::world]]
    if world > 1:
        gathered: list = [None] * world if rank == 0 else None
        dist.gather_object(mine, gathered, dst=0)
        if rank != 0:
            dist.barrier()
            return None
        results = [r for part in gathered for r in part]
    else:
        results = mine
    results.sort(key=lambda r: r["name"])
    frames = sum(r["metrics"]["frames"] for r in results)
    summary: dict = {"root": str(root), "tracker": config.tracker, "world_size": world,
                     "sequences": {r["name"]: r["metrics"] for r in results}, "frames": frames,
                     "fps_per_process": frames / sum(r["seconds"] for r in results)}
    scored = [r for r in results if r["gt"] is not None]
    if scored:
        masks = np.concatenate([r["ignore"] if r["ignore"] is not None else np.zeros(r["gt"].size, bool)
                                for r in scored])
        summary["trackers"] = {}
        for name in [config.tracker, *others]:
            pooled = concatenate([(r["gt"], r["tracks"][name][0]) for r in scored])
            tracker_s = sum(r["tracks"][name][1] for r in scored)
            summary["trackers"][name] = {**score_tracks(*pooled, config.threshold, masks),
                                         "FPS": sum(r["metrics"]["frames"] for r in scored) / max(tracker_s, 1e-9)}
        summary["aggregate"] = {**summary["trackers"][config.tracker], "sequences": len(scored)}
        if not others:
            del summary["trackers"]
    reg = [r["metrics"]["registration_error_px"]["median"] for r in results if "registration_error_px" in r["metrics"]]
    if reg:
        summary["registration_error_px"] = {"median_of_sequence_medians": float(np.median(reg)),
                                            "max_of_sequence_medians": float(np.max(reg))}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "metrics.json", summary)
    if world > 1:
        dist.barrier()
    return summary


def destroy() -> None:
    """Tear down the process group if this process started one."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()

