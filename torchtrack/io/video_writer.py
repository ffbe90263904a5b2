"""Annotated video and PNG snapshots: tracks drawn over the frames, coloured by identity, with a legend.

:func:`render_frame` draws one frame: each track as a point (or a box of ``box`` pixels) in its identity's
colour with its identity number, a short trail of its last positions, optionally the truth as small white
crosses and the detections as yellow rings, a caption (e.g. the frame number) top-left, and below the frame a
legend band that says what the colours and marks mean (:func:`legend_band`). :class:`AnnotatedVideoWriter`
streams rendered frames into an MP4 and keeps the trails; ``torchtrack draw`` and the pipeline's
``annotated.mp4`` both go through it.

The codec is H.264 (``libx264``, plays in every browser) where PyAV is installed (``pip install
torchtrack-mtt[video]``), otherwise MPEG-4 part 2 (``mp4v``, OpenCV's own encoder, which desktop players
play but browsers do not); :func:`video_codec` says which one a run gets. H.264 needs even sides, so a frame
of odd width or height is padded (black, right and bottom), never cropped.

Positions may live in another coordinate frame than the image (the pipeline's tracks live in the
registration reference): pass ``homography`` (3, 3), the map from those coordinates to the image's
pixels, and trails stay consistent while the camera moves.

The video is written under ``<name>.partial.mp4`` and renamed to its final name only by
:meth:`AnnotatedVideoWriter.close` after a normal finish, so an interrupted run never leaves a
truncated file under the final name.
"""

from __future__ import annotations

import colorsys
import importlib.util
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.geometry import apply_homography
from torchtrack.io.outputs import atomic_file, partial_name

_GOLDEN = 0.6180339887498949
_FONT = cv2.FONT_HERSHEY_SIMPLEX
TRUTH_COLOR = (255, 255, 255)
DETECTION_COLOR = (0, 220, 255)  # BGR yellow
MARKS = ("tracks", "trails", "truth", "detections")
"""What a legend can explain, in its order."""
CODECS = ("auto", "h264", "mp4v")


def identity_color(identity: int) -> tuple[int, int, int]:
    """A saturated BGR colour for ``identity``; consecutive identities get well-separated hues."""
    hue = (int(identity) * _GOLDEN) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.85, 1.0)
    return int(b * 255), int(g * 255), int(r * 255)


def video_codec(codec: str = "auto") -> str:
    """The codec a video gets: ``h264`` where PyAV (with ``libx264``) is installed, else ``mp4v``; ``codec``
    ``h264`` or ``mp4v`` asks for one (``h264`` without PyAV is an error saying what to install)."""
    if codec not in CODECS:
        raise TorchtrackError(f"video codec must be one of {', '.join(CODECS)}; got {codec!r}")
    if codec == "mp4v":
        return codec
    if importlib.util.find_spec("av") is not None:
        import av

        try:
            av.codec.Codec("libx264", "w")
            return "h264"
        except Exception:  # a PyAV build without libx264 (e.g. a system package)
            pass
    if codec == "h264":
        raise TorchtrackError("H.264 video needs PyAV with libx264: pip install 'torchtrack-mtt[video]' "
                              "(or choose mp4v)")
    return "mp4v"


def outlined_text(canvas: np.ndarray, text: str, org: tuple[int, int], font_scale: float,
                  color: tuple[int, int, int] = (255, 255, 255)) -> None:
    """Write ``text`` at ``org`` (bottom-left, px) in ``color`` with a one-pixel black outline, in place.

    The outline is the text's own mask dilated by one pixel, so it follows the glyphs exactly (text drawn
    thicker advances further per glyph and left dark ghosts of the last characters beside the caption)."""
    (w, h), base = cv2.getTextSize(text, _FONT, font_scale, 1)
    x0, y0 = max(org[0] - 2, 0), max(org[1] - h - 2, 0)
    x1, y1 = min(org[0] + w + 3, canvas.shape[1]), min(org[1] + base + 3, canvas.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.putText(mask, text, (org[0] - x0, org[1] - y0), _FONT, font_scale, 255, 1, cv2.LINE_AA)
    halo = cv2.dilate(mask, np.ones((3, 3), np.uint8)).astype(np.float32)[..., None] / 255
    alpha = mask.astype(np.float32)[..., None] / 255
    roi = canvas[y0:y1, x0:x1].astype(np.float32) * (1 - halo)
    canvas[y0:y1, x0:x1] = np.rint(roi * (1 - alpha) + np.array(color, np.float32) * alpha).astype(np.uint8)


def _cross(canvas: np.ndarray, cx: int, cy: int, r: int, color, shift: int) -> None:
    cv2.line(canvas, (cx - r, cy), (cx + r, cy), color, 1, cv2.LINE_AA, shift)
    cv2.line(canvas, (cx, cy - r), (cx, cy + r), color, 1, cv2.LINE_AA, shift)


def legend_band(width: int, marks: Sequence[str], trail: int = 0, scale: int = 1) -> np.ndarray:
    """A dark band, ``width`` px wide, that explains ``marks`` (any of :data:`MARKS`): a coloured dot with its
    number is a track and its identity, a line its last ``trail`` positions, a white cross the truth, a yellow
    ring a detection. Items wrap onto more lines where the band is narrow; uint8 BGR ``(H, width, 3)``."""
    unknown = set(marks) - set(MARKS)
    if unknown:
        raise TorchtrackError(f"legend: unknown marks {sorted(unknown)}; known: {', '.join(MARKS)}")
    s = max(1, int(scale))
    font_scale, line_h, sym_w, pad = 0.38 * s, 16 * s, 22 * s, 6 * s
    texts = {"tracks": "track (colour and number: identity)",
             "trails": f"its last {trail} positions" if trail else "its trail",
             "truth": "truth", "detections": "detection"}
    items = [(m, texts[m]) for m in MARKS if m in marks]
    placed, x, row = [], pad, 0
    for mark, text in items:
        w = sym_w + cv2.getTextSize(text, _FONT, font_scale, 1)[0][0] + 2 * pad
        if x + w > width and x > pad:
            x, row = pad, row + 1
        placed.append((mark, text, x, row))
        x += w
    band = np.full(((row + 1) * line_h + 2 * s, width, 3), 32, np.uint8)
    hue = identity_color(1)
    for mark, text, x, r in placed:
        cy = r * line_h + line_h // 2 + s
        if mark == "tracks":
            cv2.circle(band, (x + 6 * s, cy), max(2, int(2.5 * s)), hue, -1, cv2.LINE_AA)
        elif mark == "trails":
            cv2.line(band, (x, cy + 3 * s), (x + 14 * s, cy - 3 * s), hue, 1, cv2.LINE_AA)
        elif mark == "truth":
            _cross(band, x + 6 * s, cy, 3 * s, TRUTH_COLOR, 0)
        else:
            cv2.circle(band, (x + 6 * s, cy), 4 * s, DETECTION_COLOR, 1, cv2.LINE_AA)
        cv2.putText(band, text, (x + sym_w, cy + 4 * s), _FONT, font_scale, (230, 230, 230), 1, cv2.LINE_AA)
    return band


def render_frame(image: np.ndarray, ids: np.ndarray, positions: np.ndarray,
                 trails: dict[int, deque] | None = None, truth: np.ndarray | None = None,
                 homography: np.ndarray | None = None, box: int | None = None, scale: int = 1,
                 label: str | None = None, detections: np.ndarray | None = None) -> np.ndarray:
    """Draw tracks on a copy of ``image`` and return it (uint8 BGR, ``scale`` times larger).

    ``ids (K,)`` integer identities, ``positions (K, 2)`` ``[x, y]`` (column, row) in the coordinates
    that ``homography`` maps to the image, ``trails`` identity → recent positions (same coordinates),
    ``truth (M, 2)`` truth positions and ``detections (D, 2)`` detections in the same coordinates, ``box`` the
    side of the drawn box in pixels (``None``: a filled dot), ``label`` a caption (e.g. the frame number)
    written top-left.
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

    if detections is not None and len(detections):
        ring = int(4 * s * f)
        for cx, cy in fixed(apply_homography(np.asarray(detections, np.float64), homography)).tolist():
            cv2.circle(canvas, (cx, cy), ring, DETECTION_COLOR, 1, cv2.LINE_AA, shift)
    if truth is not None and len(truth):
        r = int(3 * s * f)
        for cx, cy in fixed(apply_homography(np.asarray(truth, np.float64), homography)).tolist():
            _cross(canvas, cx, cy, r, TRUTH_COLOR, shift)
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
        cv2.putText(canvas, str(identity), org, _FONT, font_scale, color, 1, cv2.LINE_AA)
    if label:
        outlined_text(canvas, label, (4, 14), 0.45)
    return canvas


def even_padded(frame: np.ndarray) -> np.ndarray:
    """``frame`` with a black column and/or row added where its width or height is odd (H.264's 4:2:0
    sampling needs even sides); never cropped."""
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return cv2.copyMakeBorder(frame, 0, h % 2, 0, w % 2, cv2.BORDER_CONSTANT, value=(0, 0, 0))


def save_png(path: str | Path, image: np.ndarray, compression: int = 3) -> Path:
    """Write ``image`` as a PNG (zlib ``compression`` 0–9), creating the folder; the file appears whole; error
    names the file."""
    path = Path(path)
    with atomic_file(path) as tmp:
        if not cv2.imwrite(str(tmp), image, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]):
            raise TorchtrackError(f"{path}: could not write PNG")
    return path


class FramePainter:
    """Draws a run frame after frame (:func:`render_frame`), keeping each identity's trail of its last ``trail``
    positions (an identity unseen for ``trail`` frames is forgotten), with the legend band of ``legend`` (the
    marks it explains, :data:`MARKS`; ``None``: no band) under every frame; ``box`` and ``scale`` as in
    :func:`render_frame`."""

    def __init__(self, trail: int = 12, box: int | None = None, scale: int = 1,
                 legend: Sequence[str] | None = None) -> None:
        self.trail_len, self.box, self.scale = int(trail), box, int(scale)
        self.legend = None if legend is None else tuple(legend)
        self.trails: dict[int, deque] = {}
        self._last_seen: dict[int, int] = {}
        self._band: np.ndarray | None = None
        self.frames = 0

    def paint(self, image: np.ndarray, ids, positions, truth=None, homography=None, label: str | None = None,
              detections=None) -> np.ndarray:
        """The next frame drawn (uint8 BGR; the legend band below it where there is one)."""
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
        frame = render_frame(image, ids, positions, self.trails, truth, homography, self.box, self.scale, label,
                             detections)
        if self.legend is not None:
            if self._band is None or self._band.shape[1] != frame.shape[1]:
                self._band = legend_band(frame.shape[1], self.legend, self.trail_len, self.scale)
            frame = np.vstack([frame, self._band])
        return frame


class _H264:
    """H.264 (``libx264``, 4:2:0) into an MP4 through PyAV, with the index at the front (``faststart``) so that
    browsers start playing before the whole file has arrived."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int]) -> None:
        import av

        self._av = av
        self._container = av.open(str(path), "w", format="mp4", options={"movflags": "faststart"})
        self._stream = self._container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        self._stream.width, self._stream.height = size
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"preset": "veryfast", "crf": "23"}

    def write(self, frame: np.ndarray) -> None:
        for packet in self._stream.encode(self._av.VideoFrame.from_ndarray(frame, format="bgr24")):
            self._container.mux(packet)

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()

    abort = close  # the partial file then plays up to the last frame written


class _Mp4v:
    """MPEG-4 part 2 (``mp4v``) through OpenCV's own writer: no extra package, but browsers do not play it."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int]) -> None:
        self._writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
        if not self._writer.isOpened():
            raise TorchtrackError(f"{path}: OpenCV cannot open an mp4v video writer")

    def write(self, frame: np.ndarray) -> None:
        self._writer.write(frame)

    def close(self) -> None:
        self._writer.release()

    abort = close


class AnnotatedVideoWriter:
    """Streams annotated frames into an MP4, keeping each identity's trail.

    Use as a context manager, or call :meth:`close` after the last :meth:`write`; leaving the ``with``
    block by an exception keeps the ``.partial.mp4`` file and does not rename it.

    Args:
        path: final ``.mp4`` path.
        fps: frame rate written in the container.
        trail: number of past positions drawn per identity (0: none).
        box: side of the drawn box in pixels, ``None`` for dots.
        scale: integer up-scaling of the output (small frames become legible).
        background: encode in a background thread (the encoders release the GIL while encoding, so the
            encoding of frame ``k`` overlaps the processing of frame ``k + 1``); at most 4 frames wait.
        legend: the marks that the legend band under every frame explains (:data:`MARKS`; ``None``: no band).
        codec: ``auto`` (H.264 where available, else mp4v), ``h264`` or ``mp4v`` (:func:`video_codec`).
    """

    def __init__(self, path: str | Path, fps: float = 10.0, trail: int = 12, box: int | None = None,
                 scale: int = 1, background: bool = True, legend: Sequence[str] | None = None,
                 codec: str = "auto") -> None:
        self.path = Path(path)
        if self.path.suffix.lower() != ".mp4":
            raise TorchtrackError(f"{self.path}: the annotated video must be an .mp4 file")
        self.partial = partial_name(self.path)
        self.fps = float(fps)
        self.codec = video_codec(codec)
        self.painter = FramePainter(trail, box, scale, legend)
        self._encoder: _H264 | _Mp4v | None = None
        self.size: tuple[int, int] | None = None  # (width, height) of the video, padded to even sides
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="video-encoder") if background else None
        self._pending: deque[Future] = deque()

    @property
    def trails(self) -> dict[int, deque]:
        """Identity → its last positions (:class:`FramePainter`)."""
        return self.painter.trails

    @property
    def frames(self) -> int:
        """Frames written so far."""
        return self.painter.frames

    def _wait(self, keep: int) -> None:
        """Wait until at most ``keep`` frames are being encoded; an encoding error is raised here."""
        while len(self._pending) > keep:
            try:
                self._pending.popleft().result()
            except Exception as exc:
                raise TorchtrackError(f"{self.partial}: video encoding failed: {exc}") from exc

    def write(self, image: np.ndarray, ids, positions, truth=None, homography=None,
              label: str | None = None, detections=None) -> np.ndarray:
        """Draw one frame (:meth:`FramePainter.paint`), append it to the video and return it (as drawn,
        unpadded)."""
        frame = self.painter.paint(image, ids, positions, truth, homography, label, detections)
        padded = even_padded(frame)
        h, w = padded.shape[:2]
        if self._encoder is None:
            self.partial.parent.mkdir(parents=True, exist_ok=True)
            self._encoder = (_H264 if self.codec == "h264" else _Mp4v)(self.partial, self.fps, (w, h))
            self.size = (w, h)
        elif (w, h) != self.size:
            raise TorchtrackError(f"{self.path}: frame {self.frames} is {w}x{h}, the video is "
                                  f"{self.size[0]}x{self.size[1]}")
        if self._pool is not None:
            self._pending.append(self._pool.submit(self._encoder.write, padded))
            self._wait(4)
        else:
            self._encoder.write(padded)
        return frame

    def close(self) -> Path:
        """Finish the file and give it its final name; returns the path."""
        if self._encoder is None:
            raise TorchtrackError(f"{self.path}: no frame was written")
        self._wait(0)
        if self._pool is not None:
            self._pool.shutdown()
        self._encoder.close()
        self._encoder = None
        self.partial.replace(self.path)
        return self.path

    def abort(self) -> None:
        """Stop without renaming: the ``.partial.mp4`` file stays, marked incomplete."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
        if self._encoder is not None:
            try:
                self._encoder.abort()
            except Exception:  # an encoder that already failed has nothing left to release
                pass
            self._encoder = None

    def __enter__(self) -> AnnotatedVideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and self._encoder is not None:
            self.close()
        else:
            self.abort()
