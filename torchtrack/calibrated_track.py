"""``torchtrack.track``: :func:`torchtrack.pipeline.api.track`, calibrated first on the input's first frames when
``calibrate=N`` is given (:mod:`torchtrack.tuning`; docs/calibrate.md). It sits above the pipeline and the
calibration, which the pipeline does not import."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from torchtrack.errors import TorchtrackError
from torchtrack.io.frames import open_frames
from torchtrack.pipeline.api import MOTInput, TrackResult, as_mot
from torchtrack.pipeline.api import track as track_pipeline
from torchtrack.pipeline.config import PipelineConfig, load_pipeline_config
from torchtrack.tuning.calibration import calibrate as calibrate_detections
from torchtrack.tuning.video import calibrate_frames, pipeline_with


def track(frames: Any = None, video: str | os.PathLike | None = None, detections: MOTInput | None = None, *,
          calibrate: int | None = None, seed: int = 0, **options: Any) -> TrackResult:
    if calibrate is None:
        return track_pipeline(frames, video, detections, **options)
    if options.get("config") is not None:
        raise TorchtrackError("calibrate sets the trackers' options itself; it does not combine with config")
    out, force = options.pop("out", None), options.pop("force", False)
    say = progress_line if options.get("progress") else None
    if detections is not None:
        det = as_mot(detections, "detections")
        first = int(det.frame.min()) if det.size else 1
        result = calibrate_detections(det, (first, first + calibrate - 1), None, seed, progress=say)
        tracked = track_pipeline(detections=det, config=result.sections, **options)
    else:
        if video is None and not isinstance(frames, str | os.PathLike):
            raise TorchtrackError("calibrate needs frames as a folder, or a video file")
        given = options.pop("pipeline_config", None)
        config = given if isinstance(given, PipelineConfig) else load_pipeline_config(given)
        source = open_frames(Path(video if video is not None else frames))
        result = calibrate_frames(source, config, calibrate, seed, say)
        tracked = track_pipeline(frames, video, pipeline_config=pipeline_with(config, result), **options)
    name = str(detections if isinstance(detections, str | os.PathLike) else video or frames or "detections")
    folder = Path(tempfile.mkdtemp(prefix="calibration-", dir=tracked._scratch.name))
    tracked.files.update(result.write(folder, name))
    tracked.calibration = result.record(name)
    if out is not None:
        tracked.save(out, force)
    return tracked


CALIBRATE_DOC = """        calibrate: first calibrate the trackers on the first ``calibrate`` frames without truth (as
            ``torchtrack track --calibrate N``): on a detection file, on its detections there; on frames (a
            folder) or a video, on the detections the pipeline gives its tracker there. The trackers then run
            with the result (``config`` must not be given); ``seed`` drives the calibration's bootstrap; the
            result's ``files`` and ``calibration`` hold what it wrote (``calibration["status"]``: ``ok``,
            ``retried`` or ``defaults``, whether the fit passed its checks).

"""
track.__doc__ = (track_pipeline.__doc__ or "").replace("\n\n    Returns:", "\n" + CALIBRATE_DOC + "    Returns:", 1)


def progress_line(line: str) -> None:
    """A calibration's progress line, on stderr."""
    print(f"calibrate: {line}", file=sys.stderr)
