"""``torchtrack draw``: any MOTChallenge tracks file (and optionally its truth and detections) drawn over the
frames it was made from, into an annotated MP4 or a folder of PNGs, with a legend.

The drawing is the pipeline's own (:class:`~torchtrack.io.video_writer.FramePainter`, which its
``annotated.mp4`` goes through): each track a dot (or box) in its identity's colour with its number and a trail
of its last positions, truth as white crosses, detections as yellow rings, the frame number top-left, and a
legend band under the frame. Positions are the box centres of the files, in the frames' pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torchtrack.errors import TorchtrackError
from torchtrack.io.frames import FrameSource
from torchtrack.io.mot import MOTData
from torchtrack.io.video_writer import AnnotatedVideoWriter, FramePainter, save_png


@dataclass
class Drawn:
    """What :func:`draw` wrote: ``frames`` drawn, the video ``path`` (or the PNG folder), its ``codec``
    (``h264`` or ``mp4v``; None for PNGs) and the ``size`` ``(width, height)`` of a frame as written (the
    legend band included; a video's padded to even sides)."""

    frames: int
    path: Path
    codec: str | None
    size: tuple[int, int]


def _by_frame(data: MOTData | None) -> dict[int, np.ndarray]:
    """Frame number → the row indices of ``data`` in that frame."""
    if data is None or data.size == 0:
        return {}
    frames = data.frames()
    return dict(zip(frames.tolist(), data.split(frames)))


def draw(source: FrameSource, tracks: MOTData, out: str | Path, truth: MOTData | None = None,
         detections: MOTData | None = None, *, png: bool = False, fps: float = 10.0, trail: int = 12,
         box: int | None = None, scale: int = 1, codec: str = "auto", names: dict[str, str] | None = None,
         progress: bool = True) -> Drawn:
    """Draw ``tracks`` (and ``truth``, ``detections``) over every frame of ``source`` (frame ``k`` of a file is
    the ``k``-th frame, from 1) into the MP4 ``out`` or, with ``png``, into ``out/frame_000001.png`` ...

    ``trail`` past positions per identity, ``box`` the side of a drawn box (None: dots), ``scale`` an integer
    up-scaling, ``fps`` and ``codec`` (:func:`~torchtrack.io.video_writer.video_codec`) those of the video;
    ``names`` maps ``tracks``, ``truth`` and ``detections`` to the file names that errors cite. A file that
    refers to frames beyond the source is an error, raised before the video gets its final name.
    """
    names = {"tracks": "tracks", "truth": "truth", "detections": "detections", **(names or {})}
    out = Path(out)
    legend = ["tracks", *(["trails"] if trail else []), *(["truth"] if truth is not None else []),
              *(["detections"] if detections is not None else [])]
    rows = {"tracks": _by_frame(tracks), "truth": _by_frame(truth), "detections": _by_frame(detections)}
    centres = {"tracks": tracks.centers(), "truth": None if truth is None else truth.centers(),
               "detections": None if detections is None else detections.centers()}
    writer = None if png else AnnotatedVideoWriter(out, fps=fps, trail=trail, box=box, scale=scale, legend=legend,
                                                   codec=codec)
    painter = FramePainter(trail, box, scale, legend) if png else writer.painter
    frames, size = 0, (0, 0)
    try:
        for frame in tqdm(source, total=len(source) or None, desc="draw", unit="frame", disable=not progress,
                          leave=False):
            k = frame.index
            at = {key: rows[key].get(k, np.empty(0, np.int64)) for key in rows}
            ids, positions = tracks.id[at["tracks"]], centres["tracks"][at["tracks"]]
            extra = {key: None if centres[key] is None else centres[key][at[key]] for key in ("truth", "detections")}
            if png:
                drawn = painter.paint(frame.image, ids, positions, label=f"frame {k}", **extra)
                save_png(out / f"frame_{k:06d}.png", drawn)
            else:
                drawn = writer.write(frame.image, ids, positions, label=f"frame {k}", **extra)
            frames, size = k, (drawn.shape[1], drawn.shape[0])
        if frames == 0:
            raise TorchtrackError(f"{source.path}: no frames")
        for key, data in (("tracks", tracks), ("truth", truth), ("detections", detections)):
            if data is not None and data.size and int(data.frame.max()) > frames:
                raise TorchtrackError(f"{names[key]}: refers to frames up to {int(data.frame.max())}, but "
                                      f"{source.path} has only {frames} frames")
        if writer is not None:
            writer.close()
            size = writer.size
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    return Drawn(frames, out, None if png else writer.codec, size)
