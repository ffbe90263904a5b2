"""torchtrack draw and the drawing the pipeline's annotated video shares: odd sizes padded (never cropped), every
frame written, a legend under the frames, H.264 where PyAV is installed, a caption without stray dark glyphs."""

import importlib.util

import cv2
import numpy as np
import pytest

from torchtrack.cli import main
from torchtrack.io.mot import from_points, write_motdata
from torchtrack.io.video_writer import identity_color, legend_band, render_frame, video_codec

W, H, N = 585, 101, 5  # an odd width and height
HAS_H264 = importlib.util.find_spec("av") is not None and video_codec() == "h264"


@pytest.fixture
def sequence(tmp_path):
    """N grey frames with a white last column (x = W - 1), two tracks, the truth and the detections."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(1, N + 1):
        image = np.full((H, W), 90, np.uint8)
        image[:, W - 1] = 255
        cv2.imwrite(str(frames / f"{k:03d}.png"), image)
    k = np.arange(1, N + 1)
    x = 100.0 + 20 * k
    write_motdata(tmp_path / "tracks.txt", from_points(np.r_[k, k], np.r_[np.full(N, 4), np.full(N, 9)],
                                                       np.r_[x, 400 - x], np.r_[np.full(N, 40.0), np.full(N, 70.0)]))
    write_motdata(tmp_path / "gt.txt", from_points(k, np.full(N, 1), x + 1, np.full(N, 40.0)))
    write_motdata(tmp_path / "det.txt", from_points(k, np.full(N, -1), x - 1, np.full(N, 41.0)))
    return tmp_path


def _decode(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while (got := cap.read())[0]:
        frames.append(got[1])
    cap.release()
    return frames


def _draw(sequence, out, *extra):
    return main(["draw", "--tracks", str(sequence / "tracks.txt"), "--frames", str(sequence / "frames"),
                 "--gt", str(sequence / "gt.txt"), "--detections", str(sequence / "det.txt"), "--out", str(out),
                 "--no-progress", *extra])


@pytest.mark.parametrize("codec", ["mp4v", "auto"])
def test_draw_video_pads_odd_sizes_keeps_every_frame_and_has_a_legend(sequence, codec, capsys):
    out = sequence / "drawn.mp4"
    assert _draw(sequence, out, "--codec", codec) == 0
    assert out.exists() and not (sequence / "drawn.partial.mp4").exists()
    frames = _decode(out)
    assert len(frames) == N
    height, width = frames[0].shape[:2]
    assert width == W + 1 and width % 2 == 0 and height % 2 == 0  # padded, not cropped to 584
    band = legend_band(W, ["tracks", "trails", "truth", "detections"], trail=12)
    assert height == H + band.shape[0] + (H + band.shape[0]) % 2
    grey = cv2.cvtColor(frames[-1], cv2.COLOR_BGR2GRAY).astype(int)
    assert grey[H // 2, W - 1] > 200  # the input's last column survives
    assert grey[H // 2, W] < 40  # the padding column is black
    legend = grey[H + 2:H + band.shape[0] - 2, :W]
    assert np.median(legend) < 50 and (legend > 150).sum() > 100  # a dark band with text on it
    # track 9 is drawn in its colour where the file puts it in the last frame: (400 - x, 70), x = 100 + 20 N
    b, g, r = frames[-1][70, 400 - (100 + 20 * N)].astype(int)
    assert np.abs(np.array([b, g, r]) - identity_color(9)).max() < 60
    assert f"drew {N} frames" in capsys.readouterr().out


@pytest.mark.skipif(not HAS_H264, reason="PyAV with libx264 is not installed (pip install torchtrack-mtt[video])")
def test_draw_writes_h264_where_pyav_is_installed(sequence):
    import av

    out = sequence / "drawn.mp4"
    assert _draw(sequence, out) == 0
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        assert sum(1 for _ in container.decode(stream)) == N


def test_draw_over_a_video(sequence):
    video = sequence / "in.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 5.0, (W - 1, H - 1))
    for _ in range(N):
        writer.write(np.full((H - 1, W - 1, 3), 90, np.uint8))
    writer.release()
    out = sequence / "drawn.mp4"
    rc = main(["draw", "--tracks", str(sequence / "tracks.txt"), "--video", str(video), "--out", str(out),
               "--no-progress", "--trail", "0"])
    assert rc == 0 and len(_decode(out)) == N


def test_draw_pngs_one_per_frame_unpadded(sequence):
    out = sequence / "pngs"
    assert _draw(sequence, out, "--scale", "2") == 0
    pngs = sorted(out.glob("frame_*.png"))
    assert [p.name for p in pngs] == [f"frame_{k:06d}.png" for k in range(1, N + 1)]
    image = cv2.imread(str(pngs[0]))
    assert image.shape[1] == 2 * W and image.shape[0] > 2 * H  # scaled, legend below, no padding


def test_tracks_beyond_the_frames_is_an_error_and_leaves_no_video(sequence, capsys):
    write_motdata(sequence / "late.txt", from_points(np.array([N + 3]), np.array([1]), np.array([5.0]),
                                                     np.array([5.0])))
    out = sequence / "drawn.mp4"
    rc = main(["draw", "--tracks", str(sequence / "late.txt"), "--frames", str(sequence / "frames"),
               "--out", str(out), "--no-progress"])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err
    assert err.startswith("torchtrack draw: error:") and "late.txt" in err and f"only {N} frames" in err


def test_caption_outline_follows_the_glyphs():
    """Every dark pixel of the caption lies next to its white text (no dark ghost of a glyph beside it)."""
    image = np.full((30, 260), 128, np.uint8)
    drawn = cv2.cvtColor(render_frame(image, [], np.empty((0, 2)), label="labelled-gmphd  frame 12"),
                         cv2.COLOR_BGR2GRAY).astype(int)
    light = (drawn > 128 + 20).astype(np.uint8)
    dark = drawn < 128 - 20
    assert dark.sum() > 50 and light.sum() > 50
    near_light = cv2.dilate(light, np.ones((5, 5), np.uint8)).astype(bool)
    assert not (dark & ~near_light).any()
