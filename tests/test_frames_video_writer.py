"""Annotated video writer: decodable mp4, identity colours at the drawn positions, partial files."""

import cv2
import numpy as np
import pytest

from torchtrack.errors import TorchtrackError
from torchtrack.geometry import apply_homography
from torchtrack.io.video_writer import AnnotatedVideoWriter, identity_color, save_png


@pytest.mark.parametrize("background", [True, False])
def test_writes_decodable_mp4_with_colours_at_tracks(tmp_path, background):
    path = tmp_path / "annotated.mp4"
    shift = np.array([[1.0, 0, 5], [0, 1, -3], [0, 0, 1]])  # reference → image
    with AnnotatedVideoWriter(path, fps=5, trail=3, background=background) as writer:
        for k in range(6):
            image = np.full((96, 128), 40, np.uint8)
            frame = writer.write(image, [3, 7], [[20 + 4 * k, 30], [80, 60 - 2 * k]],
                                 truth=np.array([[50.0, 50.0]]), homography=shift, label=f"frame {k + 1}")
            # The dot of identity 7 is drawn in its colour where the homography sends the track.
            x, y = apply_homography(np.array([[80, 60 - 2 * k]]), shift)[0]
            assert tuple(int(c) for c in frame[int(round(y)), int(round(x))]) == identity_color(7)
    assert path.exists() and not writer.partial.exists()
    cap = cv2.VideoCapture(str(path))
    decoded = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        decoded.append(img)
    cap.release()
    assert len(decoded) == 6 and decoded[0].shape == (96, 128, 3)
    # Background stays grey, the annotation is coloured (lossy codec: compare loosely).
    assert abs(int(decoded[-1][90, 5].mean()) - 40) < 6
    assert len(writer.trails[3]) == 3


def test_interrupted_video_is_left_partial(tmp_path):
    path = tmp_path / "annotated.mp4"
    with pytest.raises(RuntimeError):
        with AnnotatedVideoWriter(path) as writer:
            writer.write(np.zeros((32, 32), np.uint8), [1], [[5, 5]])
            raise RuntimeError("stop")
    assert not path.exists() and (tmp_path / "annotated.partial.mp4").exists()


def test_distinct_colours_and_png(tmp_path):
    colours = {identity_color(i) for i in range(1, 30)}
    assert len(colours) == 29
    out = save_png(tmp_path / "sub" / "snap.png", np.zeros((8, 8, 3), np.uint8))
    assert cv2.imread(str(out)).shape == (8, 8, 3)
    with pytest.raises(TorchtrackError, match="must be an .mp4"):
        AnnotatedVideoWriter(tmp_path / "a.avi")
