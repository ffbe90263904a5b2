"""The enhanced GM-PHD that follows its input: one :class:`~torchtrack.filters.gmphd_tracker.GMPHDTracker` for
detections with the detector's velocities and one for positions only (the options of
:attr:`~torchtrack.filters.tracker_config.GMPHDConfig.positions_only`).

The first frame of a stream picks the tracker: ``velocities`` given (even for an empty frame) → the
with-velocity options, None → the positions-only ones; the choice holds until :meth:`InputAwareGMPHD.reset`
(a detection source gives velocities on every frame or on none).
"""

from __future__ import annotations

from torch import Tensor

from torchtrack.filters.gmphd import MixtureState
from torchtrack.filters.gmphd_tracker import GMPHDTracker


class InputAwareGMPHD:
    """Streams through ``with_velocity`` or ``positions_only`` (None: the same tracker for both inputs)."""

    def __init__(self, with_velocity: GMPHDTracker, positions_only: GMPHDTracker | None = None):
        self.with_velocity = with_velocity
        self.positions_only = positions_only if positions_only is not None else with_velocity
        self.active = with_velocity
        self._chosen = False

    def reset(self) -> None:
        """Forget all tracks; the next frame chooses the tracker again."""
        self.with_velocity.reset()
        self.positions_only.reset()
        self.active, self._chosen = self.with_velocity, False

    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None,
             tones: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`GMPHDTracker.step` of the tracker this stream's input chose."""
        if not self._chosen:
            self.active = self.with_velocity if velocities is not None else self.positions_only
            self._chosen = True
        return self.active.step(frame, positions, velocities, tones)

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
        return self.active.cap_hits
