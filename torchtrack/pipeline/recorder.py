"""The end of every tracker stream: the final tracks kept in memory for scoring and appended to a
MOTChallenge file as they come.

A :class:`TrackRecorder` takes one frame at a time (frame coordinates). Each frame also goes to its file
(when it has one, through :class:`~torchtrack.io.mot.MOTWriter`: under its partial name until the recorder
is closed after a normal finish, so an interrupted run leaves ``NAME.partial.txt`` complete up to the last
frame recorded and never a short file under the final name); :meth:`TrackRecorder.tracks` builds the
:class:`~torchtrack.io.mot.MOTData` of the whole run once, which is what the run is scored on (the file is
an output, never read back).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from torchtrack.io.mot import MOTData, MOTWriter, concat_mot, from_points


class TrackRecorder:
    """Tracks (or detections) of a run, frame by frame: in memory, and in ``path`` where given.

    ``record(index, ids, positions)`` with ``ids (N,)`` and frame-coordinate ``positions (N, 2)``; detections
    add their ``scores (N,)`` and ``velocities (N, 2)``. Use as a context manager (the file is closed at the
    end); :meth:`tracks` may be called after it.
    """

    def __init__(self, path: str | os.PathLike | None = None) -> None:
        self.path = None if path is None else Path(path)
        self._writer = None if path is None else MOTWriter(path)
        self._frames: list[MOTData] = []
        self._data: MOTData | None = None

    def record(self, index: int, ids: np.ndarray, positions: np.ndarray, scores: np.ndarray | None = None,
               velocities: np.ndarray | None = None) -> None:
        """Append frame ``index`` (see the class docstring)."""
        positions = np.asarray(positions, np.float64).reshape(-1, 2)
        vx, vy = (None, None) if velocities is None else np.asarray(velocities, np.float64).reshape(-1, 2).T
        self._frames.append(from_points(np.full(len(positions), int(index)), ids, positions[:, 0], positions[:, 1],
                                        conf=scores, vx=vx, vy=vy))
        self._data = None
        if self._writer is not None:
            self._writer.write_frame(index, ids, positions[:, 0], positions[:, 1], conf=scores, vx=vx, vy=vy)

    def tracks(self) -> MOTData:
        """Everything recorded, in recording order."""
        if self._data is None:
            self._data = concat_mot(self._frames)
            self._frames = [self._data]
        return self._data

    def close(self) -> None:
        """Finish the file under its final name."""
        if self._writer is not None:
            self._writer.close()

    def __enter__(self) -> TrackRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._writer is not None:
            self._writer.__exit__(exc_type, exc, tb)
