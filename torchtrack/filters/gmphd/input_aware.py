"""The enhanced GM-PHD that follows its input: one :class:`~torchtrack.filters.gmphd.tracker.GMPHDTracker` with
the options for detections carrying the detector's velocities and one with the positions-only options
(:attr:`~torchtrack.filters.trackers.options.GMPHDConfig.positions_only`), over one stream.

Each frame picks its options: ``velocities`` given (even for a frame without detections) → the with-velocity
tracker, None → the positions-only one; the tracker that runs the frame first takes over the stream (mixture,
labels, velocity map, last frame) from the one that ran the previous frame
(:meth:`~torchtrack.filters.gmphd.tracker.GMPHDTracker.take_stream`). A detection file gives velocities on
every frame or on none; the video pipeline has none on its first frame (no previous frame to measure them).
"""

from __future__ import annotations

from torch import Tensor

from torchtrack.filters.gmphd.filter import MixtureState
from torchtrack.filters.gmphd.tracker import GMPHDTracker


class InputAwareGMPHD:
    """Streams through ``with_velocity`` or ``positions_only`` frame by frame (None: one tracker for both)."""

    def __init__(self, with_velocity: GMPHDTracker, positions_only: GMPHDTracker | None = None):
        self.with_velocity = with_velocity
        self.positions_only = positions_only if positions_only is not None else with_velocity
        self.active = with_velocity

    def reset(self) -> None:
        """Forget all tracks (labels restart at 1)."""
        self.with_velocity.reset()
        self.positions_only.reset()
        self.active = self.with_velocity

    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None,
             tones: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`GMPHDTracker.step` with the options of this frame's input."""
        tracker = self.with_velocity if velocities is not None else self.positions_only
        if tracker is not self.active:
            tracker.take_stream(self.active)
            self.active = tracker
        return tracker.step(frame, positions, velocities, tones)

    @property
    def tone_sigma(self) -> float | None:
        return self.active.tone_sigma

    @property
    def state(self) -> MixtureState:
        return self.active.state

    @property
    def pending_positions(self) -> Tensor:
        return self.active.pending_positions

    @property
    def cap_hits(self) -> int:
        """Component-cap hits of both trackers."""
        hits = self.with_velocity.cap_hits
        return hits if self.positions_only is self.with_velocity else hits + self.positions_only.cap_hits
