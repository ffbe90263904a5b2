"""Frame sources: video files, folders of images and in-memory arrays (the synthetic generator's source is
:class:`torchtrack.sim.video.SyntheticSource`).

Every source yields :class:`Frame` objects ``(index, image, name)`` one at a time (streaming, bounded
memory): ``index`` counts from 1 as in MOTChallenge files, ``image`` is ``uint8 (H, W)`` grey
(``color=False``, the default — satellite imagery and the synthetic sequences are grey) or
``uint8 (H, W, 3)`` BGR (``color=True``), and ``name`` names the file the frame came from, so that
errors and warnings can point at it.

Bad input is a :class:`~torchtrack.errors.TorchtrackError` naming the file:

* a missing path, a video OpenCV cannot open or whose first frame cannot be decoded;
* a folder without any image (a folder holding only other files is also empty);
* an image file that cannot be decoded;
* a frame whose size differs from the first frame's.

A folder that mixes images with other files is accepted: the other files are **skipped with a
warning** naming them (a ``README`` or ``gt.txt`` beside the frames is common), and hidden files are
ignored. Images are ordered by natural sort (``frame_2.png`` before ``frame_10.png``).
"""

from __future__ import annotations

import itertools
import re
import warnings
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from torchtrack.errors import TorchtrackError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".webp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".wmv")


class Frame(NamedTuple):
    """One frame: ``index`` (from 1), ``image`` uint8 ``(H, W)`` or ``(H, W, 3)``, ``name`` (its source)."""

    index: int
    image: np.ndarray
    name: str


def natural_key(name: str) -> list:
    """Sort key splitting digits from text so that ``f2`` < ``f10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _convert(image: np.ndarray, color: bool) -> np.ndarray:
    if image.dtype != np.uint8:
        # 16-bit or float imagery: scale the full range to 8 bits.
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if color:
        return image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


class FrameSource:
    """Base class: iterate to get :class:`Frame` objects; ``len()`` is the number of frames when known.

    A subclass yields ``(name, image)`` as decoded from :meth:`_images`; iterating numbers the frames from 1,
    raises when a frame's size differs from the first one's (naming both) and converts each image."""

    path: str
    shape: tuple[int, int]
    color: bool = False

    def _images(self) -> Iterator[tuple[str, np.ndarray]]:
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        first: tuple[tuple[int, int], str] | None = None
        for index, (name, image) in enumerate(self._images(), start=1):
            hw = (int(image.shape[0]), int(image.shape[1]))
            if first is None:
                first = (hw, name)
            elif hw != first[0]:
                raise TorchtrackError(
                    f"{name}: frame size {hw[1]}x{hw[0]} differs from {first[0][1]}x{first[0][0]} "
                    f"of the first frame ({first[1]}); all frames of a sequence must have the same size"
                )
            yield Frame(index, _convert(np.asarray(image), self.color), name)

    def __len__(self) -> int:
        raise NotImplementedError


class VideoSource(FrameSource):
    """Frames of a video file decoded with ``cv2.VideoCapture``.

    The file is opened and its first frame decoded at construction, so a missing, unreadable or empty
    video fails immediately with an error naming it.
    """

    def __init__(self, path: str | Path, color: bool = False) -> None:
        self.path = str(path)
        self.color = color
        p = Path(path)
        if not p.exists():
            raise TorchtrackError(f"{self.path}: no such video file")
        if p.is_dir():
            raise TorchtrackError(f"{self.path}: is a folder, not a video file (use --frames DIR)")
        cap = self._open()
        self._count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        cap.release()
        self.shape = next(self._images())[1].shape[:2]

    def __len__(self) -> int:
        """The container's frame count (``CAP_PROP_FRAME_COUNT``; may be an estimate for some codecs)."""
        return self._count

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(self.path)
        if not cap.isOpened():
            raise TorchtrackError(f"{self.path}: OpenCV cannot open this video (unknown or corrupt format)")
        return cap

    def _images(self) -> Iterator[tuple[str, np.ndarray]]:
        cap = self._open()
        index = 0
        try:
            while True:
                ok, image = cap.read()
                if not ok or image is None:
                    break
                index += 1
                yield f"{self.path} (frame {index})", image
        finally:
            cap.release()
        if index == 0:
            raise TorchtrackError(f"{self.path}: no frame could be decoded from this video")


class FolderSource(FrameSource):
    """The images of a folder in natural-sort order, decoded one at a time with ``cv2.imread``.

    Non-image files are skipped with one warning naming them; hidden files are ignored; a folder
    without images is an error. The first image is decoded at construction to learn the frame size.
    """

    def __init__(self, path: str | Path, color: bool = False) -> None:
        self.path = str(path)
        self.color = color
        folder = Path(path)
        if not folder.exists():
            raise TorchtrackError(f"{self.path}: no such folder")
        if not folder.is_dir():
            raise TorchtrackError(f"{self.path}: is not a folder (use --video FILE for a video)")
        entries = [e for e in folder.iterdir() if not e.name.startswith(".")]
        images = [e for e in entries if e.is_file() and e.suffix.lower() in IMAGE_SUFFIXES]
        others = sorted((e.name for e in entries if e not in images), key=natural_key)
        if not images:
            what = f" (it holds only: {', '.join(others[:5])}{', ...' if len(others) > 5 else ''})" if others else ""
            raise TorchtrackError(f"{self.path}: folder contains no image files{what}; "
                                  f"expected one of {', '.join(IMAGE_SUFFIXES)}")
        if others:
            shown = ", ".join(others[:5]) + (f" and {len(others) - 5} more" if len(others) > 5 else "")
            warnings.warn(f"{self.path}: skipping {len(others)} non-image entr"
                          f"{'y' if len(others) == 1 else 'ies'}: {shown}", stacklevel=2)
        self.files: list[Path] = sorted(images, key=lambda e: natural_key(e.name))
        self.skipped: list[str] = others
        self.shape = _read_image(self.files[0]).shape[:2]

    def __len__(self) -> int:
        return len(self.files)

    def _images(self) -> Iterator[tuple[str, np.ndarray]]:
        return ((str(file), _read_image(file)) for file in self.files)


def _read_image(file: Path) -> np.ndarray:
    """Decode ``file`` from its bytes: the name is opened by Python, which takes any name the file system gives
    (bytes that are not UTF-8 included), never by OpenCV's ``imread``, which crashes on such a name."""
    try:
        data = np.fromfile(file, dtype=np.uint8)
    except OSError as exc:
        raise TorchtrackError(f"{file}: cannot read: {exc.strerror or exc}") from exc
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None or image.size == 0:
        raise TorchtrackError(f"{file}: cannot decode this image file")
    return image


class ArraySource(FrameSource):
    """Frames held in memory (a list of arrays or an ``(T, H, W[, 3])`` array), e.g. from a generator."""

    def __init__(self, images: Sequence[np.ndarray] | np.ndarray, name: str = "<array>",
                 color: bool = False) -> None:
        if len(images) == 0:
            raise TorchtrackError(f"{name}: no frames")
        self.images = images
        self.path = name
        self.color = color
        self.shape = (int(images[0].shape[0]), int(images[0].shape[1]))

    def __len__(self) -> int:
        return len(self.images)

    def _images(self) -> Iterator[tuple[str, np.ndarray]]:
        return ((f"{self.path}[{index}]", image) for index, image in enumerate(self.images, start=1))


class FirstFrames(FrameSource):
    """The first ``count`` frames of ``source``."""

    def __init__(self, source: FrameSource, count: int) -> None:
        self.source, self.count = source, count
        self.path, self.shape, self.color = source.path, source.shape, source.color

    def __len__(self) -> int:
        return min(self.count, len(self.source))

    def _images(self) -> Iterator[tuple[str, np.ndarray]]:
        return itertools.islice(self.source._images(), self.count)


def open_frames(path: str | Path, color: bool = False) -> FrameSource:
    """A :class:`FolderSource` for a folder, else a :class:`VideoSource` (errors name ``path``)."""
    return FolderSource(path, color=color) if Path(path).is_dir() else VideoSource(path, color=color)


def prefetch(frames: Iterable[Frame], size: int = 2) -> Iterator[Frame]:
    """Iterate ``frames`` with up to ``size`` frames decoded ahead in a background thread (OpenCV
    releases the GIL while decoding, so reading overlaps the caller's work). Errors of the source are
    raised in the caller's thread, at the frame where they happened."""
    source, done = iter(frames), object()
    pool = ThreadPoolExecutor(1, thread_name_prefix="frame-prefetch")
    ahead = deque(pool.submit(next, source, done) for _ in range(size))
    try:
        while (frame := ahead.popleft().result()) is not done:
            ahead.append(pool.submit(next, source, done))
            yield frame
    finally:
        pool.shutdown(cancel_futures=True)
