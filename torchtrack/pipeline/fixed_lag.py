"""Fixed-lag output of a streaming tracker: a frame's tracks are final ``lag`` frames after it.

An online tracker decides about frame ``k`` knowing frames ``≤ k``. Waiting ``L`` frames before writing
frame ``k`` lets the pipeline correct three systematic losses with what the next frames showed
(:class:`FixedLagTracks`; every tracker of the comparison gets the same treatment):

1. **backfill** — a track reported for the first time at frame ``k`` was usually detected before it was
   confirmed: walking back from its detection at ``k`` along the detector's velocity, each earlier frame's
   detection within ``distance`` px of ``p − v`` that no reported track holds is given the new identity
   (at most ``L`` frames back);
2. **gap filling** — an identity reported again after a gap of at most ``L`` frames gets positions
   interpolated linearly across the gap;
3. **trimming** — a position with no detection within ``distance`` px (the tracker coasting) is kept only
   if the same identity has a detection within the next ``L`` frames: the coasting tail of a track whose
   vehicle has gone is dropped, coasting through a short miss is kept (positions of the last ``L``
   frames of the stream, whose future is unknown, are kept);
4. **leaving out tracks beside older ones on a cluttered video** (``merge_distance`` > 0) — on a frame
   within ``merge_age`` frames of one where the moving-object gate had to be raised (``cluttered``: the
   plain gate passed more than its budget of the pixels, misregistration or parallax showing as change),
   an identity first reported fewer than ``merge_age`` frames ago that lies within ``merge_distance`` px
   of an identity reported before it is left out of that frame: on such video a new track beside an
   established one is a second response to the same vehicle or to the clutter around it. On clean video
   (never cluttered) nothing is left out: new tracks beside old ones there are vehicles meeting.

Everything is in the tracker's (reference) coordinates. Memory is bounded: ``L`` frames of tracks and
detections plus the identities seen in the last ``L + 1`` frames and the set of identities ever reported.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from torchtrack.errors import TorchtrackError


class LaggedFrame(NamedTuple):
    """The final tracks of one frame: ``ids (N,)`` and reference ``positions (N, 2)``."""

    index: int
    ids: np.ndarray
    positions: np.ndarray


@dataclass
class _Pending:
    index: int
    ids: list[int]
    positions: list[np.ndarray]
    supported: list[bool]
    detections: np.ndarray   # (K, 2) the tracker's input positions
    velocities: np.ndarray   # (K, 2) their velocities (NaN: unknown)
    cluttered: bool = False  # within merge_age frames of a frame whose gate was raised (item 4)

    def holds(self, point: np.ndarray, distance: float) -> bool:
        """Whether a reported track of this frame lies within ``distance`` of ``point``."""
        return bool(self.positions) and float(np.min(np.hypot(*(np.asarray(self.positions) - point).T))) < distance

    def add(self, ident: int, position: np.ndarray, supported: bool) -> None:
        self.ids.append(ident)
        self.positions.append(np.asarray(position, np.float64))
        self.supported.append(supported)


def _nearest(points: np.ndarray, target: np.ndarray) -> tuple[int, float]:
    d = np.hypot(points[:, 0] - target[0], points[:, 1] - target[1])
    i = int(np.argmin(d))
    return i, float(d[i])


@dataclass
class FixedLagTracks:
    """Streaming fixed-lag correction of a tracker's output (module docstring).

    ``push`` one frame at a time (its reported tracks and the detections the tracker was given), in
    increasing frame order; it returns the frames that became final (those ``lag`` frames back), and
    ``finish`` returns the rest. ``lag = 0`` passes every frame through unchanged at once.
    """

    lag: int = 3
    distance: float = 3.0
    merge_distance: float = 0.0
    merge_age: int = 10
    _first: dict = field(default_factory=dict, init=False)     # id -> the frame it was first reported
    _cluttered_at: float = field(default=-np.inf, init=False)   # the last frame pushed as cluttered
    _pending: deque = field(default_factory=deque, init=False)
    _last: dict = field(default_factory=dict, init=False)      # id -> (frame, position) of its last report
    _known: set = field(default_factory=set, init=False)       # every identity reported so far

    def __post_init__(self) -> None:
        if self.lag < 0 or self.distance <= 0:
            raise TorchtrackError(f"FixedLagTracks needs lag >= 0 and distance > 0, got {self.lag}, {self.distance}")

    def push(self, index: int, ids: np.ndarray, positions: np.ndarray, detections: np.ndarray,
             velocities: np.ndarray, cluttered: bool = False) -> list[LaggedFrame]:
        """Frame ``index``: the tracker's ``ids (N,)`` and ``positions (N, 2)``, its input ``detections
        (K, 2)`` with their ``velocities (K, 2)``, and whether the moving-object gate was raised on it
        (``cluttered``, item 4). Returns the frames final now."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        positions = np.asarray(positions, np.float64).reshape(-1, 2)
        if self.lag == 0:
            return [LaggedFrame(index, ids, positions)]
        detections = np.asarray(detections, np.float64).reshape(-1, 2)
        velocities = np.asarray(velocities, np.float64).reshape(-1, 2)
        if cluttered:
            self._cluttered_at = index
        frame = _Pending(index, [], [], [], detections, velocities, index - self._cluttered_at <= self.merge_age)
        for ident, pos in zip(ids.tolist(), positions):
            q, d = _nearest(detections, pos) if len(detections) else (-1, np.inf)
            supported = d < self.distance
            if ident in self._last:
                self._fill_gap(ident, *self._last[ident], index, pos)
            elif ident not in self._known and supported:
                self._backfill(ident, detections[q], velocities[q], index)
            frame.add(ident, pos, supported)
            self._first.setdefault(ident, index)
            self._last[ident] = (index, pos)
            self._known.add(ident)
        self._pending.append(frame)
        self._last = {i: v for i, v in self._last.items() if v[0] >= index - self.lag}  # may fill a gap next frame
        out = []
        while len(self._pending) > self.lag:
            out.append(self._final(self._pending.popleft()))
        return out

    def finish(self) -> list[LaggedFrame]:
        """The frames still pending at the end of the stream (their unsupported positions are kept)."""
        out = [self._final(f, trim=False) for f in self._pending]
        self._pending.clear()
        return out

    def _fill_gap(self, ident: int, last_index: int, last_pos: np.ndarray, index: int, pos: np.ndarray) -> None:
        if index - last_index <= 1:
            return
        for frame in self._pending:
            if last_index < frame.index < index:
                a = (frame.index - last_index) / (index - last_index)
                frame.add(ident, last_pos + a * (pos - last_pos), False)

    def _backfill(self, ident: int, point: np.ndarray, velocity: np.ndarray, at: int) -> None:
        """Give ``ident`` the detections it came from: walk back from its detection ``point`` at frame ``at``."""
        for frame in reversed(self._pending):
            if frame.index != at - 1 or np.isnan(velocity).any() or not len(frame.detections):
                return
            q, d = _nearest(frame.detections, point - velocity)
            if d >= self.distance or frame.holds(frame.detections[q], self.distance):
                return
            point, velocity, at = frame.detections[q], frame.velocities[q], frame.index
            frame.add(ident, point, True)
            self._first[ident] = at

    def _final(self, frame: _Pending, trim: bool = True) -> LaggedFrame:
        later = {i for f in self._pending for i, s in zip(f.ids, f.supported) if s}
        keep = np.array([not trim or s or i in later for i, s in zip(frame.ids, frame.supported)], bool)
        positions = np.array(frame.positions, np.float64).reshape(-1, 2)
        ids = np.array(frame.ids, np.int64)
        if self.merge_distance > 0 and frame.cluttered:
            keep &= ~self._beside_older(frame.index, ids, positions, keep)
        return LaggedFrame(frame.index, ids[keep], positions[keep])

    def _beside_older(self, index: int, ids: np.ndarray, positions: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """``(N,)`` whether each position belongs to an identity younger than ``merge_age`` frames within
        ``merge_distance`` of an older one (item 4 of the module docstring)."""
        out = np.zeros(len(ids), bool)
        cand = np.flatnonzero(keep)
        if len(cand) < 2:
            return out
        d = np.hypot(*(positions[cand, None] - positions[None, cand]).transpose(2, 0, 1))
        for a, b in zip(*np.nonzero(np.triu(d < self.merge_distance, 1))):
            old, new = sorted((cand[a], cand[b]), key=lambda i: (self._first[ids[i]], ids[i]))
            if self._first[ids[old]] < self._first[ids[new]] and index - self._first[ids[new]] < self.merge_age:
                out[new] = True
        return out
