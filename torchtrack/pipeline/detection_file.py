"""Trackers on a detection file (``torchtrack track --detections``, ``--compare``, the WPAFB benchmark):
the frames of a MOTChallenge detection file go through the same stream as the video pipeline's
(:func:`torchtrack.pipeline.replay.run_tracker`), scored from the recorder.

A detection file has no frames to measure motion on and its positions are already in one coordinate frame,
so :func:`detection_file_config` turns the moving-object gate, the weak detections and the fixed-lag output
off and takes the trackers' options from the tracker YAML alone (built-in defaults where it has no section),
unless a pipeline config is given as its base.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from torchtrack.filters.trackers.protocol import Tracker, make_tracker
from torchtrack.io.mot import MOTData
from torchtrack.io.outputs import write_json
from torchtrack.metrics.table import score, scoring
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.frame_detections import mot_frames, stream_frames
from torchtrack.pipeline.replay import run_tracker


def detection_file_config(tracker_options: Mapping[str, dict] | None = None, threshold: float = 10.0,
                          base: PipelineConfig | None = None) -> PipelineConfig:
    """The stream settings for a detection file: ``base``'s (default: no gate, no weak detections, online
    output, every tracker at its built-in defaults), each tracker of ``tracker_options`` (tracker name →
    options) with those options, and the CLEAR-MOT ``threshold`` (px)."""
    if base is None:
        base = PipelineConfig(min_speed=0.0, min_motion=0.0, weak_threshold=None, output_lag=0, trackers={})
    return base.replace(tracker_options={}, trackers={**base.trackers, **(tracker_options or {})},
                        threshold=threshold)


def track_detections(det: MOTData, name: str, config: PipelineConfig, out: str | Path, gt: MOTData | None = None,
                     tracker: Tracker | None = None, ignore: np.ndarray | None = None) -> dict:
    """Run tracker ``name`` (``config.options_for(name)``; or the ``tracker`` given, already built, e.g. a
    fitted one) on every frame of ``det`` and ``gt``; writes ``out/tracks.txt`` and ``out/metrics.json``.
    ``ignore (K,)`` marks ``gt``'s don't-care lines (e.g. the vehicles that are not moving).

    Returns the metrics: CLEAR-MOT at ``config.threshold`` where ``gt`` is given, with ``tracker``,
    ``frames_run``, ``seconds`` and ``FPS`` (the stream alone) and, for the GM-PHD trackers, ``cap_hits``.
    """
    out = Path(out)
    if tracker is None:
        tracker = make_tracker(name, config.options_for(name))
    run = run_tracker(tracker, config, mot_frames(det, stream_frames(det, gt)), out / "tracks.txt")
    scores = {**score(gt, run.tracks, config.threshold, ignore), **scoring(ignore is not None, config.threshold)
              } if gt is not None else {}
    metrics = {"tracker": name, **scores,
               "frames_run": run.frames, "seconds": run.seconds, "FPS": run.fps}
    if hasattr(tracker, "cap_hits"):
        metrics["cap_hits"] = tracker.cap_hits
    write_json(out / "metrics.json", metrics)
    return metrics


def compare(det: MOTData, config: PipelineConfig, out: str | Path, gt: MOTData,
            trackers: Sequence[str], ignore: np.ndarray | None = None) -> dict[str, dict]:
    """Every tracker of ``trackers`` on the same detections (``out/<tracker>/``), ``gt``'s lines marked by
    ``ignore`` don't-care; tracker name → metrics."""
    return {name: track_detections(det, name, config, Path(out) / name, gt, ignore=ignore) for name in trackers}
