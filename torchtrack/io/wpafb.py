"""The WPAFB 2009 truth CSV (as published with Aguilar, Ortner & Zerubia, ICASSP 2023); the "moving" rule of
its evaluation is in :mod:`torchtrack.io.moving`.

CSV layout: header ``Frame Number,obj_<id>_px,obj_<id>_py,obj_<id>_vx,obj_<id>_vy,obj_<id>_ax,obj_<id>_ay,...``
(six columns per object), one row per frame. ``px`` is the image **row** and ``py`` the image **column**,
in pixels; an object absent from a frame has ``px = py = 0``; the velocity and acceleration columns are
zeros (unused). The file ends with a row of zeros (frame number 0), which is skipped. Columns beyond the
last named one (the published header ends with six unnamed columns) are ignored.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import POINT_BOX_SIZE, MOTData, from_points

_COLUMN = re.compile(r"obj_(\d+)_(px|py|vx|vy|ax|ay)$")
_ORDER = ("px", "py", "vx", "vy", "ax", "ay")


def read_wpafb_csv(path: str | os.PathLike, keep_frame_numbers: bool = False,
                   box: float = POINT_BOX_SIZE) -> MOTData:
    """Read the WPAFB truth CSV as MOTChallenge-style truth (point objects, ``box`` px squares).

    Frames are renumbered from 1 (the first data row becomes frame 1) unless ``keep_frame_numbers``;
    ids are the CSV's object numbers. Centres: ``cx = py`` (column), ``cy = px`` (row). Objects with
    ``px = py = 0`` are absent; all-zero rows (the trailing one) are skipped. Output sorted by frame, id.
    """
    path = Path(path)
    try:
        with open(path, encoding="utf-8") as fh:
            header = [h.strip() for h in fh.readline().strip().split(",")]
            body = fh.read()
    except OSError as exc:
        raise TorchtrackError(f"cannot read {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError:
        raise TorchtrackError(f"{path}: not UTF-8 text (expected the WPAFB truth CSV)") from None
    while header and not header[-1]:  # the published file's header ends with six unnamed columns
        header.pop()
    if not header or header[0].strip() != "Frame Number" or (len(header) - 1) % 6:
        raise TorchtrackError(f"{path}:1: expected 'Frame Number' then six columns per object")
    ids = []
    for k in range(0, len(header) - 1, 6):
        names = [_COLUMN.match(h.strip()) for h in header[1 + k:7 + k]]
        if not all(names) or len({m.group(1) for m in names}) != 1 or tuple(m.group(2) for m in names) != _ORDER:
            raise TorchtrackError(f"{path}:1: columns {k + 2}-{k + 7} are not obj_<id>_px,py,vx,vy,ax,ay")
        ids.append(int(names[0].group(1)))
    rows = []
    for lineno, line in enumerate(body.splitlines(), start=2):
        if not line.strip():
            continue
        fields = line.strip().split(",")
        if len(fields) < len(header):
            raise TorchtrackError(f"{path}:{lineno}: expected {len(header)} fields, got {len(fields)}")
        try:
            rows.append(np.array(fields[: len(header)], dtype=np.float64))
        except ValueError:
            raise TorchtrackError(f"{path}:{lineno}: not a number") from None
    if not rows:
        raise TorchtrackError(f"{path}: no data rows")
    a = np.stack(rows)
    a = a[np.any(a != 0, axis=1)]  # the trailing all-zero row
    frame_numbers = a[:, 0]
    if np.any(frame_numbers != np.round(frame_numbers)) or np.any(np.diff(frame_numbers) <= 0):
        raise TorchtrackError(f"{path}: frame numbers must be increasing integers")
    px = a[:, 1::6]  # (frames, objects) rows
    py = a[:, 2::6]  # columns
    present = (px != 0) | (py != 0)
    fi, oi = np.nonzero(present)
    frames = frame_numbers.astype(np.int64)[fi]
    if not keep_frame_numbers:
        frames = frames - int(frame_numbers[0]) + 1
    return from_points(frames, np.asarray(ids, dtype=np.int64)[oi], py[fi, oi], px[fi, oi], box=box).sorted()
