"""Adapting the detector to a video without labels (``torchtrack train-detector --adapt``).

Self-training in rounds. Round ``r``:

1. the pipeline (:func:`~torchtrack.pipeline.track_video.track_video`: registration, detector with the
   current weights, moving-object gate, tracker, fixed-lag output) runs over the frames;
2. its confident tracks become pseudo-labels (:mod:`torchtrack.pipeline.pseudo_labels`: identities kept over
   ``min_length`` frames, positions and velocities linked frame to frame in the registered video);
3. when they changed by less than ``stop_change`` since the previous round (the share of pseudo-labels of
   either round without one of the other within ``radius`` px in the same frame) the rounds stop;
4. otherwise the weights are fine-tuned on them (:func:`torchtrack.detector.finetune.finetune`): synthetic
   pairs mixed in (``finetune.synthetic_share``) so that the original skill stays, and the neighbourhood of
   every detection of the current weights that no pseudo-label explains — a peak the tracker did not
   confirm: unsure — masked out of the loss (``finetune.unlabelled_static: dont_care``), so that it counts
   neither as a vehicle nor as background. The fine-tuned weights are written as ``round-r/weights.pt``
   (the shipped weights' format) and used by the next round.

``report.json`` (per round: pseudo-labels, tracks, change, fine-tune loss, seconds) and ``adapt.png`` are
rewritten after every round. Same frames, weights and seed: same result.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from torchtrack.detector.checkpoint import load_checkpoint
from torchtrack.detector.config import FinetuneConfig
from torchtrack.detector.finetune import finetune
from torchtrack.detector.inference import DEFAULT_WEIGHTS
from torchtrack.detector.labelled import LabelledFrames
from torchtrack.detector.region import Region
from torchtrack.detector.train import export_weights
from torchtrack.errors import TorchtrackError
from torchtrack.io.frames import ArraySource, FrameSource
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.plots import plot_rounds
from torchtrack.pipeline.pseudo_labels import pseudo_labels
from torchtrack.pipeline.track_video import track_video


@dataclasses.dataclass(frozen=True)
class AdaptSettings:
    """rounds: at most this many fine-tunes; min_length: frames a track must be kept to be a pseudo-label;
    stop_change: stop when the pseudo-labels changed by less than this share; radius: px within which two
    rounds' pseudo-labels are the same."""

    rounds: int = 3
    min_length: int = 8
    stop_change: float = 0.05
    radius: float = 2.0


def load_frames(source: FrameSource, name: str) -> np.ndarray:
    """Every frame of ``source`` as ``(T, H, W)`` uint8 grey (the source refuses frames of another size); fewer
    than two frames is an error naming ``name`` (the argument and path)."""
    frames = [frame.image for frame in source]
    if len(frames) < 2:
        raise TorchtrackError(f"{name}: {len(frames)} frame(s); adapting needs a video")
    return np.stack(frames)


def label_change(a: LabelledFrames, b: LabelledFrames, radius: float) -> float:
    """The share of the points of ``a`` and ``b`` (frame by frame) without a point of the other within
    ``radius`` px (0: the same labels; 1: nothing in common)."""
    unmatched = total = 0
    for p, q in zip(a.xy, b.xy):
        total += len(p) + len(q)
        for x, y in ((p, q), (q, p)):
            if len(x):
                unmatched += len(x) if not len(y) else int((cKDTree(y).query(x)[0] > radius).sum())
    return unmatched / total if total else 0.0


def adapt(frames: np.ndarray, out: str | Path, weights: str | Path | None = None,
          settings: AdaptSettings = AdaptSettings(), finetune_config: FinetuneConfig | None = None,
          pipeline: PipelineConfig | None = None, seed: int = 0, progress: bool = True, log=print) -> dict:
    """Adapt ``weights`` (default: the shipped ones) to ``frames (T, H, W)`` uint8 (module docstring); writes
    under ``out``; returns the report (``rounds``, ``weights``: the last weights' path relative to ``out``,
    ``seconds``)."""
    started = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = load_checkpoint(DEFAULT_WEIGHTS if weights is None else weights)
    f = finetune_config or base["config"].finetune
    f = dataclasses.replace(f, unlabelled_static="dont_care")
    pipe = (pipeline or PipelineConfig()).replace(video=False)
    h, w = frames.shape[1:]
    current, state = str(DEFAULT_WEIGHTS if weights is None else weights), base["model"]
    report: dict = {"frames": len(frames), "size": [h, w], "seed": seed, "settings": dataclasses.asdict(settings),
                    "start": current, "rounds": []}
    previous = None
    for r in range(1, settings.rounds + 1):
        t0 = time.perf_counter()
        run = track_video(ArraySource(list(frames)), out / f"round-{r}" / "pipeline",
                          pipe.replace(detector_weights=current), keep_detections=True, progress=False)
        labels = pseudo_labels(frames, run.tracks, [d.homography for d in run.detections], settings.min_length)
        count = sum(len(p) for p in labels.xy)
        if count == 0:
            raise TorchtrackError(f"no track was kept over {settings.min_length} frames in {len(frames)} frames "
                                  "(too short a video, or nothing moves): no pseudo-labels to adapt to")
        change = 1.0 if previous is None else label_change(previous, labels, settings.radius)
        row = {"round": r, "pseudo_labels": count, "tracks": int(len(np.unique(np.concatenate(labels.ids)))),
               "change": change}
        log(f"round {r}: {count} pseudo-labels from {row['tracks']} tracks, changed {100 * change:.1f} %")
        if previous is not None and change < settings.stop_change:
            row["stopped"] = True
            report["rounds"].append({**row, "seconds": time.perf_counter() - t0})
            break
        cfg = dataclasses.replace(base["config"], finetune=dataclasses.replace(f, out=str(out / f"round-{r}")))
        tuned = finetune(cfg, state, labels, Region(0, 0, w, h), seed=seed + r, progress=progress, log=log)
        current = str(export_weights(tuned["last"], out / f"round-{r}" / "weights.pt",
                                     {"seed": seed, "adapted_from": report["start"], "round": r}))
        state = load_checkpoint(current)["model"]
        previous = labels
        report["rounds"].append({**row, "loss": tuned["history"][-1]["loss"],
                                 "weights": str(Path(current).relative_to(out)), "seconds": time.perf_counter() - t0})
        _write_report(out, report)
    report["weights"] = str(Path(current).relative_to(out))
    report["seconds"] = time.perf_counter() - started
    _write_report(out, report)
    return report


def _write_report(out: Path, report: dict) -> None:
    (out / "report.json").write_text(json.dumps(report, indent=2))
    plot_rounds(report["rounds"], out / "adapt.png")
