"""MOTChallenge text files: reading, writing, and an incremental per-frame writer.

Format, one object per line, comma separated (whitespace is accepted too)::

    frame, id, x, y, w, h, conf, c8, c9, c10

- ``frame`` counts from 1 (0 is accepted, negative numbers are not); ``id`` is the track / truth id, or
  ``-1`` for an unlabelled detection. Both must be integers (``3`` or ``3.0``, not ``3.5``).
- ``x, y`` is the box's **top-left** corner, ``w, h`` its size, in pixels; ``x`` is the column, ``y`` the
  row. Point objects (vehicles in WAMI, simulated detections, tracker output) get a fixed box of
  :data:`POINT_BOX_SIZE` pixels centred on the point, so the centre is ``(x + w/2, y + h/2)``.
- ``conf`` is the confidence (absent → 1). In ground truth, ``conf`` 0 marks an object to ignore
  (MOTChallenge's convention; :func:`torchtrack.metrics.clear_mot` honours it).
  ``c8, c9, c10`` are the MOTChallenge 3-D world coordinates,
  ``-1,-1,-1`` for 2-D data.
- **Velocity (torchtrack extension).** Detection files that carry a velocity per detection (the
  CenterTrack-style detector's velocity head, or ``torchtrack simulate-detections --velocity-sigma``)
  store it in ``c8, c9`` as ``vx, vy`` in pixels per frame (``vx`` along columns, ``vy`` along rows),
  keeping ``c10 = -1``. A file whose ``c8, c9`` are ``-1`` on every line, or absent, carries no velocity:
  :func:`read_mot` then returns ``vx = vy = None``. Readers therefore accept both kinds of file.

Lines may have 6 to 10 fields; blank lines and lines starting with ``#`` are skipped. A malformed line is
a :class:`~torchtrack.errors.TorchtrackError` naming the file and the line number. Two lines with the
same frame and the same (non-negative) id are an error too.
"""

from __future__ import annotations

import itertools
import os
import re
import warnings
from array import array
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import partial_name, write_text

POINT_BOX_SIZE = 8.0
"""Side in pixels of the square box written around point objects (vehicles in WAMI are 3–7 px across)."""

_SPLIT = re.compile(r"[,\s]+")


class MOTData(NamedTuple):
    """Objects of a MOTChallenge file as flat numpy arrays of length K (one entry per line).

    ``frame, id`` int64; ``x, y, w, h, conf`` float64 (``x, y`` the top-left corner, column and row);
    ``vx, vy`` float64 velocities in px/frame, or None when the file carries no velocity.
    """

    frame: np.ndarray
    id: np.ndarray
    x: np.ndarray
    y: np.ndarray
    w: np.ndarray
    h: np.ndarray
    conf: np.ndarray
    vx: np.ndarray | None = None
    vy: np.ndarray | None = None

    @property
    def size(self) -> int:
        """Number of objects K (``len()`` of a MOTData is its number of fields, as for any tuple)."""
        return int(self.frame.shape[0])

    def centers(self) -> np.ndarray:
        """(K, 2) box centres: column ``x + w/2``, row ``y + h/2``."""
        return np.stack([self.x + 0.5 * self.w, self.y + 0.5 * self.h], axis=1)

    def boxes(self) -> np.ndarray:
        """(K, 4) boxes ``x, y, w, h``."""
        return np.stack([self.x, self.y, self.w, self.h], axis=1)

    def as_written(self) -> MOTData:
        """The same objects with the box coordinates a MOTChallenge file of :func:`format_lines` holds (three
        decimals), so that scores of this data equal those of the file read back (HOTA's similarity thresholds
        can tell 1e-4 px apart)."""
        rounded = [np.array([float(f"{v:.3f}") for v in a], np.float64) for a in (self.x, self.y, self.w, self.h)]
        return self._replace(x=rounded[0], y=rounded[1], w=rounded[2], h=rounded[3])

    def velocity(self) -> np.ndarray | None:
        """(K, 2) velocity ``vx, vy`` in px/frame, or None."""
        if self.vx is None or self.vy is None:
            return None
        return np.stack([self.vx, self.vy], axis=1)

    def frames(self) -> np.ndarray:
        """Sorted distinct frame numbers present in the data."""
        return np.unique(self.frame)

    def select(self, index: np.ndarray) -> MOTData:
        """The objects picked by a boolean mask or an index array."""
        return MOTData(*(None if a is None else a[index] for a in self))

    def sorted(self) -> MOTData:
        """The same objects ordered by frame, then id (stable)."""
        return self.select(np.lexsort((self.id, self.frame)))

    def split(self, frames: Iterable[int] | None = None) -> list[np.ndarray]:
        """Index arrays of the objects of each frame, for ``frames`` (default :meth:`frames`)."""
        frames = self.frames() if frames is None else np.asarray(list(frames), dtype=np.int64)
        order = np.argsort(self.frame, kind="stable")
        sorted_frames = self.frame[order]
        lo = np.searchsorted(sorted_frames, frames, side="left")
        hi = np.searchsorted(sorted_frames, frames, side="right")
        return [order[a:b] for a, b in zip(lo, hi)]


def empty_mot(with_velocity: bool = False) -> MOTData:
    """A MOTData with no objects."""
    frame_and_id = [np.zeros(0, dtype=np.int64) for _ in range(2)]
    floats = [np.zeros(0, dtype=np.float64) for _ in range(7 if with_velocity else 5)]  # x y w h conf (vx vy)
    return MOTData(*frame_and_id, *floats)


def concat_mot(items: Sequence[MOTData]) -> MOTData:
    """The objects of ``items`` one after the other (velocities kept only where every item has them)."""
    if not items:
        return empty_mot()
    return MOTData(*(None if any(getattr(m, name) is None for m in items)
                     else np.concatenate([getattr(m, name) for m in items]) for name in MOTData._fields))


def from_points(
    frames, ids, cx, cy, box: float = POINT_BOX_SIZE, conf=None, vx=None, vy=None
) -> MOTData:
    """MOTData of point objects with centres ``(cx, cy)`` and a ``box`` × ``box`` square around each.

    All arguments are array-likes of length K (numpy arrays, lists or tensors); ``conf`` defaults to 1.
    """
    frames = _as_int_array(frames, "frames")
    ids = _as_int_array(ids, "ids")
    cx = _as_float_array(cx, "cx")
    cy = _as_float_array(cy, "cy")
    k = frames.shape[0]
    for name, a in (("ids", ids), ("cx", cx), ("cy", cy)):
        if a.shape[0] != k:
            raise TorchtrackError(f"{name} has {a.shape[0]} entries, frames has {k}")
    conf = np.ones(k) if conf is None else _as_float_array(conf, "conf")
    if (vx is None) != (vy is None):
        raise TorchtrackError("give both vx and vy, or neither")
    if vx is not None:
        vx, vy = _as_float_array(vx, "vx"), _as_float_array(vy, "vy")
    size = np.full(k, float(box))
    return MOTData(frames, ids, cx - 0.5 * box, cy - 0.5 * box, size, size.copy(), conf, vx, vy)


def as_rows(data: MOTData) -> np.ndarray:
    """``(K, 10)`` float64 MOTChallenge rows of ``data``, sorted by frame then id, as :func:`write_motdata`
    writes them (velocity in columns 8 and 9 where ``data`` has one, else ``-1``; column 10 ``-1``)."""
    data = data.sorted()
    rows = np.full((data.size, 10), -1.0)
    rows[:, :7] = np.stack([data.frame, data.id, data.x, data.y, data.w, data.h, data.conf], axis=1)
    if data.vx is not None and data.vy is not None:
        rows[:, 7], rows[:, 8] = data.vx, data.vy
    return rows


def from_rows(rows, name: str = "rows") -> MOTData:
    """MOTData from an array of MOTChallenge rows ``(K, 6..10)`` (``frame, id, x, y, w, h[, conf, c8, c9, c10]``,
    the columns of a file): conf 1 where absent, velocity from ``c8, c9`` by the rule of :func:`read_mot`.
    Errors name ``name``."""
    rows = _numpy(rows, np.float64)
    if rows.ndim != 2 or not 6 <= rows.shape[1] <= 10:
        raise TorchtrackError(f"{name}: expected MOTChallenge rows of shape (K, 6..10), got {tuple(rows.shape)}")
    if not np.all(np.isfinite(rows)):
        raise TorchtrackError(f"{name}: NaN or infinite values")
    full = np.full((rows.shape[0], 9), -1.0)
    full[:, 6] = 1.0
    full[:, :rows.shape[1] - (rows.shape[1] == 10)] = rows[:, :9]
    frame, ident = _as_int_array(full[:, 0], f"{name} frame"), _as_int_array(full[:, 1], f"{name} id")
    if np.any(frame < 0) or np.any(ident < -1):
        raise TorchtrackError(f"{name}: frames must be >= 0 and ids >= 0 (or -1 for a detection)")
    return _with_velocity(frame, ident, *full[:, 2:9].T.copy())


def as_mot(value: str | os.PathLike | MOTData | np.ndarray, name: str) -> MOTData:
    """A MOTChallenge file's path, a :class:`MOTData` or an array of its rows (:func:`from_rows`) as
    :class:`MOTData`; ``name`` names an array in errors."""
    if isinstance(value, MOTData):
        return value
    if isinstance(value, str | os.PathLike):
        return read_mot(value)
    return from_rows(value, name)


def _numpy(a, dtype: type | None = None) -> np.ndarray:
    """An array-like or a tensor as a numpy array."""
    return np.asarray(a.detach().cpu() if hasattr(a, "detach") else a, dtype=dtype)


def _as_float_array(a, name: str) -> np.ndarray:
    out = _numpy(a, np.float64).reshape(-1)
    if not np.all(np.isfinite(out)):
        raise TorchtrackError(f"{name} contains NaN or infinite values")
    return out


def _as_int_array(a, name: str) -> np.ndarray:
    arr = _numpy(a)
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise TorchtrackError(f"{name} must be integers")
    return arr.astype(np.int64).reshape(-1)


def _bad(path: Path, lineno: int, msg: str) -> TorchtrackError:
    return TorchtrackError(f"{path}:{lineno}: {msg}")


def _integer(field: str, what: str, path: Path, lineno: int) -> int:
    """``field`` as an exact integer (``3`` or ``3.0``; ids above 2**53 stay exact), within int64."""
    try:
        value = int(field)
    except ValueError:
        try:
            number = float(field)
        except ValueError:
            raise _bad(path, lineno, f"{what} is not a number: {field!r}") from None
        if not np.isfinite(number) or number != int(number):
            raise _bad(path, lineno, f"{what} must be an integer, got {field!r}") from None
        value = int(number)
    if not -(2**63) <= value < 2**63:
        raise _bad(path, lineno, f"{what} {field} is outside the 64-bit integer range")
    return value


_CHUNK_LINES = 1024
"""Lines parsed per :func:`numpy.loadtxt` call by :func:`_read_uniform`: the memory it needs beside the result."""


def _read_uniform(path: Path) -> tuple[np.ndarray | None, ...] | None:
    """The columns of a file whose every line holds the same number (6 to 10) of comma-separated valid numbers,
    parsed in C (:func:`numpy.loadtxt`, :data:`_CHUNK_LINES` lines at a time into typed columns: about three
    times faster than :func:`_read_lines`, in the same memory), as ``(frame, id, x, y, w, h, conf, c8, c9,
    None)`` (line numbers are the positions + 1); None for anything else (comments, blank lines, whitespace
    separators, a bad value, ids beyond 2**53): :func:`_read_lines` then reads it, naming any bad line."""
    ints, floats, width = [array("q"), array("q")], [array("d") for _ in range(7)], None
    defaults = np.array([1.0, -1.0, -1.0])  # conf, c8, c9 where the lines stop short
    try:
        with open(path, encoding="utf-8") as handle, warnings.catch_warnings():
            warnings.simplefilter("error")  # numpy warns (rather than fails) on some malformed input
            while lines := list(itertools.islice(handle, _CHUNK_LINES)):
                table = np.loadtxt(lines, delimiter=",", comments=None, ndmin=2)
                if table.shape[0] != len(lines) or width not in (None, table.shape[1]) or not 6 <= table.shape[1] <= 10:
                    return None
                width, ids = table.shape[1], table[:, :2]
                if not (np.isfinite(table).all() and (np.abs(ids) < 2**53).all() and (ids == np.round(ids)).all()
                        and (ids[:, 0] >= 0).all() and (ids[:, 1] >= -1).all() and (table[:, 4:6] >= 0).all()):
                    return None
                for column, k in zip(ints, range(2)):
                    column.frombytes(table[:, k].astype(np.int64).tobytes())
                for column, k in zip(floats, range(2, 9)):
                    values = table[:, k] if k < width else np.full(len(lines), defaults[k - 6])
                    column.frombytes(np.ascontiguousarray(values).tobytes())
    except (OSError, ValueError, UnicodeError, Warning):
        return None
    if width is None:
        return None
    return (*(np.frombuffer(c, dtype=np.int64) for c in ints), *(np.frombuffer(c, dtype=np.float64) for c in floats),
            None)


def _read_lines(path: Path) -> tuple[np.ndarray, ...]:
    """The columns of any MOTChallenge file, read line by line into typed columns (8 bytes a value, so memory
    stays near the size of the result), as ``(frame, id, x, y, w, h, conf, c8, c9, line numbers)``."""
    frames, ids, linenos = array("q"), array("q"), array("q")
    values = [array("d") for _ in range(7)]        # x, y, w, h, conf, c8, c9
    try:
        with open(path, "rb") as handle:
            for lineno, raw in enumerate(handle, start=1):
                try:
                    line = raw.decode("utf-8").strip()
                except UnicodeDecodeError:
                    raise _bad(path, lineno, "not UTF-8 text (a binary file?)") from None
                if not line or line.startswith("#"):
                    continue
                fields = [f for f in _SPLIT.split(line) if f]
                if not 6 <= len(fields) <= 10:
                    raise _bad(path, lineno, f"expected 6 to 10 fields (frame,id,x,y,w,h,...), got {len(fields)}")
                frame = _integer(fields[0], "frame", path, lineno)
                ident = _integer(fields[1], "id", path, lineno)
                if frame < 0:
                    raise _bad(path, lineno, f"frame must be a non-negative integer, got {fields[0]!r}")
                if ident < -1:
                    raise _bad(path, lineno, f"id must be an integer >= 0 (or -1 for a detection), got {fields[1]!r}")
                try:
                    vals = [float(f) for f in fields[2:]]
                except ValueError:
                    raise _bad(path, lineno, f"not a number in {line!r}") from None
                if not all(np.isfinite(vals)):
                    raise _bad(path, lineno, f"NaN or infinite value in {line!r}")
                if vals[2] < 0 or vals[3] < 0:
                    raise _bad(path, lineno, f"negative box size in {line!r}")
                vals = (vals + [1.0, -1.0, -1.0][len(vals) - 4:])[:7]  # default conf, absent c8, c9; drop c10
                frames.append(frame)
                ids.append(ident)
                linenos.append(lineno)
                for column, v in zip(values, vals):
                    column.append(v)
    except OSError as exc:
        raise TorchtrackError(f"cannot read {path}: {exc.strerror or exc}") from exc
    return (np.frombuffer(frames, dtype=np.int64), np.frombuffer(ids, dtype=np.int64),
            *(np.frombuffer(c, dtype=np.float64) for c in values), np.frombuffer(linenos, dtype=np.int64))


def read_mot(path: str | os.PathLike) -> MOTData:
    """Read a MOTChallenge text file (see the module docstring for the format and the velocity rule).

    Raises TorchtrackError naming the file and line for a malformed line (bytes that are not UTF-8, too
    few or too many fields, non-numbers, NaN/inf, negative, non-integer or beyond-int64 frame, non-integer
    id or a negative id other than -1, negative box size) and for a repeated (frame, id) pair. An empty
    file gives an empty MOTData. Plain files (every line the same number of comma-separated valid numbers)
    are parsed in C, any other line by line.
    """
    path = Path(path)
    frame, ident, x, y, w, h, conf, c8, c9, linenos = _read_uniform(path) or _read_lines(path)
    if not frame.size:
        return empty_mot()
    labelled = np.flatnonzero(ident >= 0)
    if labelled.size:
        order = labelled[np.lexsort((ident[labelled], frame[labelled]))]
        dup = np.flatnonzero((np.diff(frame[order]) == 0) & (np.diff(ident[order]) == 0))
        if dup.size:
            first, second = sorted((order[dup[0]], order[dup[0] + 1]))
            at = (first + 1, second + 1) if linenos is None else (linenos[first], linenos[second])
            raise _bad(path, at[1], f"frame {frame[second]} id {ident[second]} already given on line {at[0]}")
    return _with_velocity(frame, ident, x, y, w, h, conf, c8, c9)


def _with_velocity(frame, ident, x, y, w, h, conf, c8: np.ndarray, c9: np.ndarray) -> MOTData:
    """The objects with ``c8, c9`` as their velocity, or none where every line holds ``-1, -1`` (module docstring)."""
    has_velocity = bool(np.any(c8 != -1.0) or np.any(c9 != -1.0))
    return MOTData(frame, ident, x, y, w, h, conf, c8 if has_velocity else None, c9 if has_velocity else None)


def format_lines(data: MOTData) -> str:
    """The MOTChallenge text of ``data`` (no trailing newline when empty), in the order given."""
    vel = data.velocity()
    out = []
    for i in range(data.size):
        c8 = f"{vel[i, 0]:.4f},{vel[i, 1]:.4f}" if vel is not None else "-1,-1"
        out.append(f"{data.frame[i]},{data.id[i]},{data.x[i]:.3f},{data.y[i]:.3f},"
                   f"{data.w[i]:.3f},{data.h[i]:.3f},{data.conf[i]:.4g},{c8},-1\n")
    return "".join(out)


def write_mot(
    path: str | os.PathLike,
    frames,
    ids,
    cx,
    cy,
    box: float = POINT_BOX_SIZE,
    conf=None,
    vx=None,
    vy=None,
) -> None:
    """Write point objects (centres ``cx`` column, ``cy`` row) as MOTChallenge text, sorted by frame, id.

    Each line is ``frame,id,x,y,w,h,conf,-1,-1,-1`` with a ``box`` × ``box`` square centred on the
    point; with ``vx, vy`` the velocity goes to columns 8 and 9 (module docstring).
    """
    write_motdata(path, from_points(frames, ids, cx, cy, box=box, conf=conf, vx=vx, vy=vy))


def write_motdata(path: str | os.PathLike, data: MOTData) -> None:
    """Write a MOTData as MOTChallenge text, sorted by frame then id (parent folders are created; the file
    appears whole, :func:`torchtrack.io.outputs.write_text`)."""
    write_text(path, format_lines(data.sorted()))


class MOTWriter:
    """Incremental MOTChallenge writer: one :meth:`write_frame` call per frame, flushed at once.

    The lines go to ``NAME.partial.txt`` (:func:`torchtrack.io.outputs.partial_name`), each frame in a single
    write followed by a flush, and :meth:`close` renames it to ``path``: the final name only ever holds a
    whole run, and a run that is interrupted leaves the partial file complete up to the last frame written.
    Use as a context manager (leaving it by an exception closes without renaming)::

        with MOTWriter("out/tracks.txt") as w:
            for k, (ids, cx, cy) in enumerate(estimates, start=1):
                w.write_frame(k, ids, cx, cy)
    """

    def __init__(self, path: str | os.PathLike, box: float = POINT_BOX_SIZE):
        self.path = Path(path)
        self.partial = partial_name(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.box = float(box)
        self._file = open(self.partial, "w")  # noqa: SIM115 - closed in close()

    def write_frame(self, frame: int, ids, cx, cy, conf=None, vx=None, vy=None) -> None:
        """Append the objects of one frame (arrays of length n, n may be 0) and flush."""
        ids = _as_int_array(ids, "ids")
        frames = np.full(ids.shape[0], int(frame), dtype=np.int64)
        self.write_lines(from_points(frames, ids, cx, cy, box=self.box, conf=conf, vx=vx, vy=vy))

    def write_lines(self, data: MOTData) -> None:
        """Append the objects of ``data`` in the order given (one frame's, typically) and flush."""
        self._file.write(format_lines(data))
        self._file.flush()

    def close(self) -> None:
        """Finish the file and give it its final name."""
        if not self._file.closed:
            self._file.close()
            os.replace(self.partial, self.path)

    def abort(self) -> None:
        """Close without renaming: the partial file stays, marked incomplete by its name."""
        self._file.close()

    def __enter__(self) -> MOTWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
