"""End to end with the shipped detector and the real trackers on a tiny synthetic sequence (5 frames of
256 x 256; at 128 x 128 the generator's buildings fill so much of the frame that the detector's per-frame
normalisation hides the vehicles): tracks, metrics, a decodable annotated video; bad input gives clear
errors and no file that passes for a complete run."""

import json

import cv2
import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.io.mot import read_mot
from torchtrack.pipeline.demo import format_demo, run_demo
from torchtrack.sim.video import VideoConfig, write_sequence

TINY = VideoConfig(height=256, width=256, frames=5)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    return write_sequence(TINY, torch.Generator().manual_seed(20_000_001), tmp_path_factory.mktemp("seq"))


def _decode(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    return frames


def test_track_frames_end_to_end(sequence, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["track", "--frames", str(sequence / "frames"), "--gt", str(sequence / "gt.txt"),
               "--camera", str(sequence / "camera.json"), "--out", str(out), "--no-progress"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "MOTA" in printed and "registration error" in printed
    tracks = read_mot(out / "tracks.txt")
    assert tracks.size > 0 and set(tracks.frames().tolist()) <= {1, 2, 3, 4, 5}
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 5 and m["tracker"] == "gmphd"
    assert {"MOTA", "IDS", "IDF1", "MT"} <= set(m["clear_mot"])
    assert m["clear_mot"]["TP"] > 0  # the detector and tracker find vehicles that are really there
    assert m["registration_error_px"]["median"] < 0.5
    frames = _decode(out / "annotated.mp4")
    assert len(frames) == 5 and frames[0].shape[1:] == (256, 3)
    assert frames[0].shape[0] > 256  # the legend band (torchtrack draw's) under the frame


def test_video_input_and_tracker_choice(sequence, tmp_path):
    video = tmp_path / "in.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 2.0, (256, 256), False)
    for f in sorted((sequence / "frames").iterdir()):
        writer.write(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
    writer.release()
    out = tmp_path / "out"
    assert main(["track", "--video", str(video), "--tracker", "sort", "--out", str(out), "--no-video",
                 "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["tracker"] == "sort" and m["frames"] == 5 and "clear_mot" not in m
    assert not (out / "annotated.mp4").exists()


def test_truth_beyond_the_video_is_an_error(sequence, tmp_path, capsys):
    gt = read_mot(sequence / "gt.txt")
    bad = tmp_path / "gt_long.txt"
    bad.write_text((sequence / "gt.txt").read_text() + f"9,{int(gt.id.max()) + 1},10,10,10,10,1,-1,-1,-1\n")
    out = tmp_path / "out"
    rc = main(["track", "--frames", str(sequence / "frames"), "--gt", str(bad), "--out", str(out), "--no-progress"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "gt_long.txt: truth refers to frames up to 9, but the video has only 5 frames" in err
    assert not (out / "metrics.json").exists() and not (out / "annotated.mp4").exists()


@pytest.mark.parametrize("make, message", [
    (lambda p: p / "missing.mp4", "missing.mp4: no such video file"),
    (lambda p: (p / "broken.mp4").write_bytes(b"\x00" * 64) and p / "broken.mp4", "broken.mp4"),
])
def test_bad_video_named(tmp_path, capsys, make, message):
    rc = main(["track", "--video", str(make(tmp_path)), "--out", str(tmp_path / "out"), "--no-progress"])
    assert rc == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_demo_on_a_tiny_sequence(tmp_path):
    m = run_demo(tmp_path, seed=1, video_config=TINY, progress=False)
    assert {"gmphd", "labelled-gmphd", "sort", "greedy"} <= set(m["trackers"])
    for name, s in m["trackers"].items():
        assert s["GT"] == m["trackers"]["gmphd"]["GT"] > 0, name  # same truth for everyone
        assert (tmp_path / "trackers" / f"{name}.txt").exists() or name == "gmphd"
    for f in ("annotated.mp4", "tracks.txt", "metrics.json", "tracks_first_frame.png", "scores.png"):
        assert (tmp_path / f).exists(), f
    assert len(_decode(tmp_path / "annotated.mp4")) == 5
    text = format_demo(m)
    assert "MOTA (%)" in text and "labelled-gmphd" in text
    assert np.isfinite(m["fps"]["end_to_end"])
    assert (tmp_path / m["source"]).is_dir()          # relative to the output folder, true after it is moved


def test_real_wpafb_frames(tmp_path, capsys, wpafb_data):
    data = wpafb_data
    out = tmp_path / "wpafb"
    rc = main(["track", "--frames", str(data / "frames"), "--truth-csv", str(data / "transformed_object_states.csv"),
               "--out", str(out), "--no-progress"])
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 6 and m["frame_size"] == [496, 585]
    assert m["clear_mot"]["GT"] > 0  # moving vehicles (frame 1 has none: nothing has a history yet)
    assert m["detector"]["TP"] > 0  # the synthetic-trained detector finds real vehicles
    assert len(_decode(out / "annotated.mp4")) == 6


def test_weak_detections_leave_the_detector_output_and_its_prior_unchanged(sequence, tmp_path):
    """Decoding further down for the tracker adds weak detections (flagged) but changes neither the
    strong ones, nor detections.txt, nor the prior heatmap the next frame is detected with."""
    from torchtrack.detector import load_detector
    from torchtrack.io.frames import FolderSource
    from torchtrack.pipeline.config import PipelineConfig
    from torchtrack.pipeline.track_video import track_video

    threshold = load_detector().config.decode.threshold
    runs = {}
    for weak in (None, 0.1):
        cfg = PipelineConfig(weak_threshold=weak, video=False)
        runs[weak] = track_video(FolderSource(sequence / "frames"), tmp_path / str(weak), cfg,
                                 keep_detections=True, progress=False)
    assert (tmp_path / "None" / "detections.txt").read_text() == (tmp_path / "0.1" / "detections.txt").read_text()
    extra = 0
    for plain, weak in zip(runs[None].detections, runs[0.1].detections):
        assert plain.strong.all()
        np.testing.assert_array_equal(weak.select(weak.strong).image_positions, plain.image_positions)
        assert (weak.scores[~weak.strong] >= 0.1).all() and (weak.scores[~weak.strong] < threshold).all()
        extra += int((~weak.strong).sum())
    assert extra > 0
