"""One tracker over detections already made: the kept detections of a video run (the other trackers of
``demo``, ``track --sequences --compare``, ``select-trackers``) or a detection file (``track --detections``,
the WPAFB benchmark).

The frames go through the same stream as in the video pipeline (:class:`TrackerStream`: moving-object gate,
weak detections, the tracker's step, fixed-lag output) into a :class:`TrackRecorder`, back in frame
coordinates (``H_k⁻¹``).
"""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from torchtrack.geometry import apply_homography
from torchtrack.io.mot import MOTData
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.frame_detections import FrameDetections
from torchtrack.pipeline.recorder import TrackRecorder
from torchtrack.pipeline.tracker_stream import TrackerStream


@dataclass
class TrackerRun:
    """What :func:`run_tracker` produced: the ``tracks`` (frame coordinates), the ``seconds`` spent in the
    stream (the tracker, its gate and its fixed-lag output) and the ``frames`` run."""

    tracks: MOTData
    seconds: float
    frames: int

    @property
    def fps(self) -> float:
        """Frames per second of the tracker alone."""
        return self.frames / self.seconds if self.seconds > 0 else float("inf")


def run_tracker(tracker, config: PipelineConfig, detections: Iterable[FrameDetections],
                tracks_path: str | os.PathLike | None = None) -> TrackerRun:
    """Feed ``detections`` frame by frame through ``tracker`` with ``config``'s gate, weak detections and
    output lag; the final tracks are recorded (and written to ``tracks_path`` where given)."""
    stream = TrackerStream(tracker, config)
    to_frame: dict[int, np.ndarray] = {}  # H_k⁻¹ of the frames not final yet
    seconds, frames = 0.0, 0
    with TrackRecorder(tracks_path) as recorder:
        for det in itertools.chain(detections, [None]):
            t0 = time.perf_counter()
            if det is None:
                final = stream.finish()
            else:
                to_frame[det.index] = np.linalg.inv(det.homography)
                final = stream.step(det)[2]
                frames += 1
            seconds += time.perf_counter() - t0
            for frame in final:
                recorder.record(frame.index, frame.ids, apply_homography(frame.positions, to_frame.pop(frame.index)))
    return TrackerRun(recorder.tracks(), seconds, frames)
