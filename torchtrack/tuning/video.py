"""Calibration from frames or a video (``torchtrack track --frames/--video --calibrate N``, ``torchtrack calibrate
--from-frames``, ``torchtrack.track(..., calibrate=N)``; docs/calibrate.md, "From frames or a video").

The video pipeline runs on the first ``N`` frames; the detections its tracker is given there — those the
moving-object gate passes, at the detector's threshold, in the first frame's coordinates, with the detector's
velocities — are calibrated on as a detection file is (:func:`~torchtrack.tuning.calibration.calibrate`), over
the pipeline's own GM-PHD options (``trackers.gmphd`` of its configuration: the calibrated sensor and decisions go
over them, and they are what a failed fit falls back to). The first frame, which has no velocities, is left out.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable

import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.io.frames import FirstFrames, FrameSource
from torchtrack.io.mot import MOTData, from_points
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.track_video import track_video
from torchtrack.pipeline.tracker_stream import gated
from torchtrack.tuning.calibration import CalibrationResult, calibrate
from torchtrack.tuning.decisions import merged


def pipeline_detections(source: FrameSource, config: PipelineConfig, frames: int, progress: bool = False) -> MOTData:
    """The tracker's input over the first ``frames`` frames of ``source`` (module docstring), as a detection
    file in the first frame's coordinates (velocities in columns 8-9)."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="torchtrack-calibrate-") as tmp:
        run = track_video(FirstFrames(source, frames), tmp, config.replace(video=False), keep_detections=True,
                          progress=progress)
    for det in run.detections[1:]:
        given = gated(det, config)
        given = given.select(given.strong)
        rows += [(det.index, *p, *v) for p, v in zip(given.positions, given.velocities)]
    if not rows:
        raise TorchtrackError(f"{source.path}: the pipeline found no moving detection in the first {frames} "
                              "frames to calibrate on")
    f, x, y, vx, vy = np.array(rows, dtype=np.float64).T
    return from_points(f.astype(int), np.full(len(f), -1), x, y, vx=vx, vy=vy)


def calibrate_frames(source: FrameSource, config: PipelineConfig, frames: int, seed: int = 0,
                     progress: Callable[[str], None] | None = None, first: int = 1) -> CalibrationResult:
    """Calibrate the pipeline's trackers on frames ``first..frames`` of ``source`` (module docstring; the
    pipeline runs from frame 1)."""
    if frames - max(first, 2) < 2:
        raise TorchtrackError(f"calibrate on at least 3 frames after the first; got frames {first}-{frames}")
    det = pipeline_detections(source, config, frames, progress is not None)
    return calibrate(det, (max(first, 2), frames), True, seed, str(source.path), progress,
                     base=config.trackers.get("gmphd") or {})


def pipeline_with(config: PipelineConfig, result: CalibrationResult) -> PipelineConfig:
    """``config`` with its trackers' options replaced by the calibrated sections (over its own)."""
    trackers = {name: merged(config.trackers.get(name) or {}, section) for name, section in result.sections.items()}
    return config.replace(trackers={**config.trackers, **trackers}, tracker_options={})
