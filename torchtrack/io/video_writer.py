"""Annotated video and PNG snapshots: tracks drawn over the frames, coloured by identity.

:func:`render_frame` draws one frame: each track as a point (or a box of ``box`` pixels) in its
identity's colour with its identity number, a short trail of its last positions, and optionally the
truth as small white crosses. :class:`AnnotatedVideoWriter` streams rendered frames into an MP4
(``cv2.VideoWriter`` with the ``mp4v`` codec) and keeps the trails.

Positions may live in another coordinate frame than the image (the pipeline's tracks live in the
registration reference): pass ``homography`` (3, 3), the map from those coordinates to the image's
pixels, and trails stay consistent while the camera moves.

The video is written under ``<name>.partial.mp4`` and renamed to its final name only by
:meth:`AnnotatedVideoWriter.close` after a normal finish, so an interrupted run never leaves a
truncated file under the final name.
"""

from __future__ import annotations

import colorsys
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.geometry import apply_homography
from torchtrack.io.outputs import atomic_file, partial_name

_GOLDEN = 0.6180339887498949


def identity_color(identity: int) -> tuple[int, int, int]:
    """A saturated BGR colour for ``identity``; consecutive identities get well-separated hues."""
    hue = (int(identity) * _GOLDEN) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.85, 1.0)
    return int(b * 255), int(g * 255), int(r * 255)


def render_frame(image: np.ndarray, ids: np.ndarray, positions: np.ndarray,
                 trails: dict[int, deque] | None = None, truth: np.ndarray | None = None,
                 homography: np.ndarray | None = None, box: int | None = None, scale: int = 1,
                 label: str | None = None) -> np.ndarray:
    """Draw tracks on a copy of ``image`` and return it (uint8 BGR, ``scale`` times larger).

    ``ids (K,)`` integer identities, ``positions (K, 2)`` ``[x, y]`` (column, row) in the coordinates
    that ``homography`` maps to the image, ``trails`` identity → recent positions (same coordinates),
    ``truth (M, 2)`` truth positions in the same coordinates, ``box`` the side of the drawn box in
    pixels (``None``: a filled dot), ``label`` a caption (e.g. the frame number) written top-left.
    """
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else np.array(image, order="C")
    if scale != 1:
        canvas = cv2.resize(canvas, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    s = float(scale)
    shift = 4  # fixed-point sub-pixel drawing
    f = float(1 << shift)

    def fixed(xy: np.ndarray) -> np.ndarray:
        """Pixel-centre coordinates → fixed-point integer coordinates of the scaled canvas."""
        return np.rint(((xy + 0.5) * s - 0.5) * f).astype(np.int32)

    if truth is not None and len(truth):
        r = int(3 * s * f)
        for cx, cy in fixed(apply_homography(truth, homography)).tolist():
            cv2.line(canvas, (cx - r, cy), (cx + r, cy), (255, 255, 255), 1, cv2.LINE_AA, shift)
            cv2.line(canvas, (cx, cy - r), (cx, cy + r), (255, 255, 255), 1, cv2.LINE_AA, shift)
    ids = np.asarray(ids).reshape(-1).tolist()
    colors = [identity_color(i) for i in ids]
    if trails:
        for identity, color in zip(ids, colors):
            trail = trails.get(int(identity))
            if trail is not None and len(trail) > 1:
                pts = fixed(apply_homography(np.array(trail), homography))
                cv2.polylines(canvas, [pts.reshape(-1, 1, 2)], False, color, 1, cv2.LINE_AA, shift)
    font_scale = 0.35 * max(1.0, s * 0.75)
    half = int((box or 0) * s * f / 2)
    dot = int(2.5 * s * f)
    centers = fixed(apply_homography(positions, homography)).tolist()
    for identity, color, (cx, cy) in zip(ids, colors, centers):
        if box:
            cv2.rectangle(canvas, (cx - half, cy - half), (cx + half, cy + half), color, 1, cv2.LINE_AA, shift)
        else:
            cv2.circle(canvas, (cx, cy), dot, color, -1, cv2.LINE_AA, shift)
        org = (int(cx / f + 3 * s), int(cy / f - 3 * s))
        cv2.putText(canvas, str(identity), org, cv2.FONT_HERSHEY_SIMPLEX, font_scale, color, 1, cv2.LINE_AA)
    if label:
        cv2.putText(canvas, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(canvas, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


def save_png(path: str | Path, image: np.ndarray, compression: int = 3) -> Path:
    """Write ``image`` as a PNG (zlib ``compression`` 0–9), creating the folder; the file appears whole; error
    names the file."""
    path = Path(path)
    with atomic_file(path) as tmp:
        if not cv2.imwrite(str(tmp), image, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]):
            raise TorchtrackError(f"{path}: could not write PNG")
    return path


class AnnotatedVideoWriter:
    """Streams annotated frames into an MP4 (``mp4v``), keeping each identity's trail.

    Use as a context manager, or call :meth:`close` after the last :meth:`write`; leaving the ``with``
    block by an exception keeps the ``.partial.mp4`` file and does not rename it.

    Args:
        path: final ``.mp4`` path.
        fps: frame rate written in the container.
        trail: number of past positions drawn per identity (0: none).
        box: side of the drawn box in pixels, ``None`` for dots.
        scale: integer up-scaling of the output (small frames become legible).
        background: encode in a background thread (OpenCV releases the GIL while encoding, so the
            encoding of frame ``k`` overlaps the processing of frame ``k + 1``); at most 4 frames wait.
    """

    def __init__(self, path: str | Path, fps: float = 10.0, trail: int = 12, box: int | None = None,
                 scale: int = 1, background: bool = True) -> None:
        self.path = Path(path)
        if self.path.suffix.lower() != ".mp4":
            raise TorchtrackError(f"{self.path}: the annotated video must be an .mp4 file")
        self.partial = partial_name(self.path)
        self.fps, self.trail_len, self.box, self.scale = float(fps), int(trail), box, int(scale)
        self.trails: dict[int, deque] = {}
        self._last_seen: dict[int, int] = {}
        self._writer: cv2.VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        self.frames = 0
        self._encoder = ThreadPoolExecutor(1, thread_name_prefix="video-encoder") if background else None
        self._pending: deque[Future] = deque()

    def _wait(self, keep: int) -> None:
        """Wait until at most ``keep`` frames are being encoded; an encoding error is raised here."""
        while len(self._pending) > keep:
            try:
                self._pending.popleft().result()
            except Exception as exc:
                raise TorchtrackError(f"{self.partial}: video encoding failed: {exc}") from exc

    def write(self, image: np.ndarray, ids, positions, truth=None, homography=None,
              label: str | None = None) -> np.ndarray:
        """Render one frame (see :func:`render_frame`), append it to the video and return it."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        self.frames += 1
        if self.trail_len > 0:
            for identity, xy in zip(ids.tolist(), positions):
                self.trails.setdefault(identity, deque(maxlen=self.trail_len)).append(xy.copy())
                self._last_seen[identity] = self.frames
            stale = [i for i, seen in self._last_seen.items() if self.frames - seen > self.trail_len]
            for i in stale:
                del self.trails[i], self._last_seen[i]
        frame = render_frame(image, ids, positions, self.trails, truth, homography, self.box, self.scale, label)
        h, w = frame.shape[:2]
        if self._writer is None:
            self.partial.parent.mkdir(parents=True, exist_ok=True)
            self._writer = cv2.VideoWriter(str(self.partial), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
            if not self._writer.isOpened():
                raise TorchtrackError(f"{self.partial}: OpenCV cannot open an mp4v video writer")
            self._size = (w, h)
        elif (w, h) != self._size:
            raise TorchtrackError(f"{self.path}: frame {self.frames} is {w}x{h}, the video is "
                                  f"{self._size[0]}x{self._size[1]}")
        if self._encoder is not None:
            self._pending.append(self._encoder.submit(self._writer.write, frame))
            self._wait(4)
        else:
            self._writer.write(frame)
        return frame

    def close(self) -> Path:
        """Finish the file and give it its final name; returns the path."""
        if self._writer is None:
            raise TorchtrackError(f"{self.path}: no frame was written")
        self._wait(0)
        self.abort()
        self.partial.replace(self.path)
        return self.path

    def abort(self) -> None:
        """Release the writer without renaming: the ``.partial.mp4`` file stays, marked incomplete."""
        if self._encoder is not None:
            self._encoder.shutdown()
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def __enter__(self) -> AnnotatedVideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and self._writer is not None:
            self.close()
        else:
            self.abort()
