"""Step 3 of the pipeline for one tracker: what it is given, its step, and its fixed-lag output.

Per frame (:class:`TrackerStream`):

1. the **moving-object gate** (``min_speed``, ``min_motion`` raised by ``gate_registration`` times the
   difference the registration's residual leaves at the detection; :meth:`FrameDetections.moving`);
2. **weak detections that continue a track** — detections decoded below the detector's threshold
   (down to ``weak_threshold``) are given to the tracker only where they continue a track: their position
   minus their velocity lies within ``weak_distance`` px of a position the tracker reported at the previous
   frame (the two-threshold association of ByteTrack, Zhang et al., ECCV 2022, without its second
   association pass: the tracker's own association takes them) — with ``weak_continues_pending``, also of a
   new track extracted but not yet reported (``pending_positions``). They never start a track on their own;
3. the tracker's ``step`` (identities unique per frame, see :func:`run_tracker_step`) on the config's
   ``tracker_threads`` torch threads (:mod:`torchtrack.threads`), whatever the detector runs on;
4. the **fixed-lag output** (:class:`torchtrack.pipeline.fixed_lag.FixedLagTracks`, ``output_lag``
   frames, ``lag_distance`` px).
"""

from __future__ import annotations

import numpy as np
import torch

from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.fixed_lag import FixedLagTracks, LaggedFrame
from torchtrack.pipeline.frame_detections import FrameDetections, as_numpy
from torchtrack.threads import clamp_threads, torch_threads


def run_tracker_step(tracker, det: FrameDetections, dtype: torch.dtype,
                     device: torch.device | str = "cpu") -> tuple[np.ndarray, np.ndarray, int]:
    """One ``tracker.step`` on a frame's detections, given on ``device``; returns ``ids (N,)``, reference
    ``positions (N, 2)``
    and how many estimates were dropped because their identity was already reported in this frame
    (the trackers' contract is unique identities per frame; a repeat is kept out of ``tracks.txt``, which
    must stay a valid MOTChallenge file, and counted in ``metrics.json``)."""
    kw = {"dtype": dtype, "device": device}
    velocities = None if np.isnan(det.velocities).any() else torch.as_tensor(det.velocities, **kw)
    extra = {}
    if det.tones is not None and getattr(tracker, "tone_sigma", None) is not None:
        extra["tones"] = torch.as_tensor(det.tones, **kw)
    ids, positions = tracker.step(det.index, torch.as_tensor(det.positions, **kw), velocities, **extra)
    ids = as_numpy(ids, ()).astype(np.int64)
    positions = as_numpy(positions, (2,))
    keep = np.sort(np.unique(ids, return_index=True)[1])  # the first estimate of each identity
    return ids[keep], positions[keep], len(ids) - len(keep)


def gated(det: FrameDetections, config: PipelineConfig) -> FrameDetections:
    """The detections the moving-object gate of ``config`` passes (all of them where it is off)."""
    if config.min_speed > 0 or config.min_motion > 0:
        return det.moving(config.min_speed, config.min_motion, config.gate_registration, config.motion_noise_factor)
    return det


class TrackerStream:
    """A tracker fed a pipeline's :class:`FrameDetections` frame by frame (module docstring).

    ``step(det)`` returns the tracker's own (online) ``ids`` and reference ``positions`` of the frame —
    what the next frame's prior heatmap may use — and the frames whose tracks became final;
    ``finish()`` returns the frames still pending at the end. ``duplicates`` counts the estimates dropped
    for repeating an identity within a frame.
    """

    def __init__(self, tracker, config: PipelineConfig) -> None:
        self.tracker = tracker
        self.config = config
        self.dtype = getattr(torch, config.dtype)
        self.threads = clamp_threads(config.tracker_threads)
        self.output = FixedLagTracks(config.output_lag, config.lag_distance, config.merge_distance,
                                     config.merge_age)
        self.previous = np.zeros((0, 2))
        self.duplicates = 0
        self.segment = 0
        self.id_offset = 0   # identities of a new segment start above every earlier one
        self.next_id = 0

    def tracker_input(self, det: FrameDetections) -> FrameDetections:
        """The detections the tracker gets: moving, and strong or continuing a previous position."""
        moving = gated(det, self.config)
        keep = moving.strong.copy()
        weak = np.flatnonzero(~keep & (moving.scores >= (self.config.weak_threshold or np.inf)))
        if len(weak) and len(self.previous) and not np.isnan(moving.velocities).any():
            start = moving.positions[weak] - moving.velocities[weak]
            gap = np.hypot(start[:, None, 0] - self.previous[None, :, 0], start[:, None, 1] - self.previous[None, :, 1])
            keep[weak[gap.min(axis=1) < self.config.weak_distance]] = True
        return moving if keep.all() else moving.select(keep)

    def step(self, det: FrameDetections) -> tuple[np.ndarray, np.ndarray, list[LaggedFrame]]:
        """One frame: the tracker's online ``ids (N,)``, ``positions (N, 2)`` and the frames final now.
        A frame of a new registration segment ends every track: the pending frames are final at once, the
        tracker starts afresh, and its identities continue above the earlier ones."""
        done = []
        if det.segment != self.segment:
            done = self.output.finish()
            self.output = FixedLagTracks(self.config.output_lag, self.config.lag_distance,
                                         self.config.merge_distance, self.config.merge_age)
            self.tracker.reset()
            self.segment, self.id_offset, self.previous = det.segment, self.next_id, np.zeros((0, 2))
        given = self.tracker_input(det)
        with torch_threads(self.threads):
            ids, positions, dropped = run_tracker_step(self.tracker, given, self.dtype, self.config.device)
        ids = ids + self.id_offset
        if len(ids):
            self.next_id = max(self.next_id, int(ids.max()) + 1)
        self.duplicates += dropped
        self.previous = positions
        if self.config.weak_continues_pending and hasattr(self.tracker, "pending_positions"):
            self.previous = np.concatenate([positions, as_numpy(self.tracker.pending_positions, (2,))])
        return ids, positions, done + self.output.push(det.index, ids, positions, given.positions, given.velocities,
                                                                det.cluttered)

    def finish(self) -> list[LaggedFrame]:
        """The frames still pending at the end of the stream."""
        return self.output.finish()
