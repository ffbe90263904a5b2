"""Frame sources: natural order, round trips through video files, and clear errors on bad input."""

import warnings

import cv2
import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.io.frames import ArraySource, FolderSource, VideoSource, natural_key, open_frames


def _img(value: int, shape=(24, 32)) -> np.ndarray:
    return np.full(shape, value, np.uint8)


def test_folder_natural_sort(tmp_path):
    for i in (10, 2, 1):
        cv2.imwrite(str(tmp_path / f"frame_{i}.png"), _img(i))
    src = open_frames(tmp_path)
    assert isinstance(src, FolderSource) and len(src) == 3
    frames = list(src)
    assert [f.index for f in frames] == [1, 2, 3]
    assert [int(f.image[0, 0]) for f in frames] == [1, 2, 10]
    assert frames[2].name.endswith("frame_10.png")
    assert sorted(["a10", "a9", "a100"], key=natural_key) == ["a9", "a10", "a100"]


def test_folder_color_option(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), _img(7))
    (frame,) = FolderSource(tmp_path, color=True)
    assert frame.image.shape == (24, 32, 3)


def test_mixed_folder_warns_and_skips(tmp_path):
    cv2.imwrite(str(tmp_path / "f1.png"), _img(1))
    cv2.imwrite(str(tmp_path / "f2.png"), _img(2))
    (tmp_path / "gt.txt").write_text("1,1,0,0,1,1,1,-1,-1,-1\n")
    (tmp_path / ".hidden").write_text("x")
    with pytest.warns(UserWarning, match=r"skipping 1 non-image entry: gt\.txt"):
        src = FolderSource(tmp_path)
    assert len(src) == 2 and src.skipped == ["gt.txt"]


def test_empty_folder_and_only_other_files(tmp_path):
    with pytest.raises(TorchtrackError, match=f"{tmp_path}: folder contains no image files"):
        FolderSource(tmp_path)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(TorchtrackError, match="holds only: notes.txt"):
        FolderSource(tmp_path)


def test_changing_size_names_the_file(tmp_path):
    cv2.imwrite(str(tmp_path / "f1.png"), _img(1))
    cv2.imwrite(str(tmp_path / "f2.png"), _img(2, (20, 32)))
    with pytest.raises(TorchtrackError, match=r"f2\.png: frame size 32x20 differs from 32x24"):
        list(FolderSource(tmp_path))


def test_undecodable_image_named(tmp_path):
    cv2.imwrite(str(tmp_path / "f1.png"), _img(1))
    (tmp_path / "f2.png").write_bytes(b"not a png")
    src = FolderSource(tmp_path)
    with pytest.raises(TorchtrackError, match=r"f2\.png: cannot decode"):
        list(src)


def test_missing_and_unreadable_video(tmp_path):
    with pytest.raises(TorchtrackError, match="nope.mp4: no such video file"):
        VideoSource(tmp_path / "nope.mp4")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"\x00" * 1000)
    with pytest.raises(TorchtrackError, match="bad.mp4"):
        VideoSource(bad)


def test_video_round_trip(tmp_path):
    path = tmp_path / "v.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 5.0, (64, 48))
    for v in (30, 120, 220):
        writer.write(cv2.cvtColor(_img(v, (48, 64)), cv2.COLOR_GRAY2BGR))
    writer.release()
    src = open_frames(path)
    assert isinstance(src, VideoSource) and src.shape == (48, 64) and len(src) == 3
    frames = list(src)
    assert [f.index for f in frames] == [1, 2, 3]
    assert frames[0].image.shape == (48, 64)
    # Lossy codec: flat frames come back close to their value.
    assert [abs(float(f.image.mean()) - v) < 4 for f, v in zip(frames, (30, 120, 220))] == [True] * 3


def test_array_source_checks_sizes():
    with pytest.raises(TorchtrackError, match=r"<array>\[2\]: frame size"):
        list(ArraySource([_img(1), _img(2, (10, 10))]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(ArraySource(np.zeros((4, 8, 8), np.uint8)))) == 4


def test_synthetic_source_matches_generator():
    from torchtrack.sim.video import SyntheticSource, VideoConfig, generate_sequence

    cfg = VideoConfig(height=128, width=128, frames=3)
    src = SyntheticSource(cfg, torch.Generator().manual_seed(5))
    frames = list(src)
    direct = list(generate_sequence(cfg, torch.Generator().manual_seed(5)))
    assert len(src) == 3 and [f.index for f in frames] == [1, 2, 3]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(frames, direct))
    assert np.array_equal(src.truth.xy, direct[-1].xy)


def test_prefetch_keeps_order_and_raises_where_the_source_fails(tmp_path):
    from torchtrack.io.frames import prefetch

    for k in range(1, 6):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), _img(k, (24, 32) if k != 4 else (10, 10)))
    seen = []
    with pytest.raises(TorchtrackError, match=r"f4\.png: frame size"):
        for f in prefetch(FolderSource(tmp_path)):
            seen.append(int(f.image[0, 0]))
    assert seen == [1, 2, 3]
    # Stopping early leaves no thread behind blocked on a full queue.
    it = prefetch(ArraySource(np.zeros((50, 8, 8), np.uint8)), size=1)
    assert next(it).index == 1
    it.close()
