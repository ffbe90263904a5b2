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
from array import array

import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import POINT_BOX_SIZE, MOTData, MOTWriter, empty_mot, from_points

_COLUMNS = ("frame", "id", "x", "y", "conf", "vx", "vy")


class TrackRecorder:
    """Tracks (or detections) of a run, frame by frame: in memory, and in ``path`` where given.

    ``record(index, ids, positions)`` with ``ids (N,)`` and frame-coordinate ``positions (N, 2)``; detections
    add their ``scores (N,)`` and ``velocities (N, 2)`` (kept only while every frame has them). The objects are
    appended to typed columns (8 bytes a value), which :meth:`tracks` wraps without a copy, so memory stays
    near the size of the result; after :meth:`tracks`, nothing more can be recorded. Use as a context manager
    (the file is closed at the end); :meth:`tracks` may be called after it.
    """

    def __init__(self, path: str | os.PathLike | None = None, box: float = POINT_BOX_SIZE) -> None:
        self.box = float(box)
        self._writer = None if path is None else MOTWriter(path, box=box)
        self._columns = {name: array("q" if name in ("frame", "id") else "d") for name in _COLUMNS}
        self._with_velocity = True
        self._data: MOTData | None = None

    def record(self, index: int, ids: np.ndarray, positions: np.ndarray, scores: np.ndarray | None = None,
               velocities: np.ndarray | None = None) -> None:
        """Append frame ``index`` (see the class docstring)."""
        if self._data is not None:
            raise TorchtrackError("TrackRecorder: a frame recorded after tracks() was read")
        cx, cy = np.asarray(positions, np.float64).reshape(-1, 2).T
        vx, vy = (None, None) if velocities is None else np.asarray(velocities, np.float64).reshape(-1, 2).T
        frame = from_points(np.full(len(cx), int(index)), ids, cx, cy, box=self.box, conf=scores, vx=vx, vy=vy)
        self._with_velocity &= velocities is not None
        for name, column in self._columns.items():
            if self._with_velocity or name not in ("vx", "vy"):
                column.extend(getattr(frame, name))
        if self._writer is not None:
            self._writer.write_lines(frame)

    def tracks(self) -> MOTData:
        """Everything recorded, in recording order."""
        if self._data is None:
            n = len(self._columns["frame"])
            if n == 0:
                self._data = empty_mot()
            else:
                data = {name: np.frombuffer(column, np.int64 if column.typecode == "q" else np.float64)
                        for name, column in self._columns.items()}
                if not self._with_velocity:
                    data["vx"] = data["vy"] = None
                self._data = MOTData(**data, w=np.full(n, self.box), h=np.full(n, self.box))
        return self._data

    def __enter__(self) -> TrackRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._writer is not None:
            self._writer.__exit__(exc_type, exc, tb)
