"""The Python API (torchtrack.track, torchtrack.evaluate) against the commands' own outputs: each input form
(frames, video, detection file, in-memory rows) gives the tracks and scores that ``torchtrack track`` writes, and
``evaluate`` the scores of ``torchtrack eval``."""

import json

import cv2
import numpy as np
import pytest
import torch
from test_baselines_track_cli import scene

import torchtrack
from torchtrack.cli import main
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.sort import SORT
from torchtrack.io.mot import from_rows, read_mot
from torchtrack.pipeline.api import EXTRAS
from torchtrack.sim.video import VideoConfig, write_sequence

TINY = VideoConfig(height=256, width=256, frames=5)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    return write_sequence(TINY, torch.Generator().manual_seed(20_000_001), tmp_path_factory.mktemp("seq"))


def _rows(path):
    """A MOTChallenge file's rows ordered by frame, then id (stable: detections keep the file's order)."""
    rows = np.loadtxt(path, delimiter=",", ndmin=2)
    return rows[np.lexsort((rows[:, 1], rows[:, 0]))]


def _same_scores(metrics: dict, written: dict) -> None:
    """``TrackResult.metrics`` holds what ``metrics.json`` says, timings aside."""
    timing = {"seconds", "FPS"}
    assert {k: v for k, v in metrics.items() if k not in timing} == {k: written[k] for k in metrics if k not in timing}


def test_detection_file_and_rows_equal_the_command(tmp_path, capsys):
    gt, det = scene(tmp_path)
    out = tmp_path / "cmd"
    assert main(["track", "--detections", str(det), "--gt", str(gt), "--out", str(out)]) == 0
    result = torchtrack.track(detections=det, gt=gt)
    np.testing.assert_allclose(result.tracks, _rows(out / "tracks.txt"), atol=6e-4)
    _same_scores(result.metrics, json.loads((out / "metrics.json").read_text()))
    np.testing.assert_array_equal(result.detections, _rows(det))          # the input, as rows
    # the same detections as an array of rows, and the truth as rows: the same tracks
    from_array = torchtrack.track(detections=_rows(det), gt=_rows(gt))
    np.testing.assert_allclose(from_array.tracks, result.tracks, atol=6e-4)
    assert from_array.metrics["MOTA"] == pytest.approx(result.metrics["MOTA"])
    assert torchtrack.track(detections=det).metrics is None


def test_save_writes_the_commands_files_as_one_set(tmp_path):
    gt, det = scene(tmp_path)
    result = torchtrack.track(detections=det, gt=gt, tracker="sort")
    files = result.save(tmp_path / "saved")
    assert sorted(p.name for p in files.values()) == ["metrics.json", "tracks.txt"]
    np.testing.assert_allclose(_rows(files["tracks"]), result.tracks, atol=6e-4)
    # the folder is the command's: torchtrack track may replace it without --force
    assert main(["track", "--detections", str(det), "--out", str(tmp_path / "saved")]) == 0


def test_a_tracker_object_runs_as_given(tmp_path):
    gt, det = scene(tmp_path)
    by_name = torchtrack.track(detections=det, gt=gt, tracker="sort")
    by_object = torchtrack.track(detections=det, gt=gt, tracker=SORT())
    np.testing.assert_array_equal(by_object.tracks, by_name.tracks)
    assert by_object.report["tracker"] == "SORT"


def test_frames_and_video_equal_the_command(sequence, tmp_path, capsys):
    out = tmp_path / "cmd"
    assert main(["track", "--frames", str(sequence / "frames"), "--gt", str(sequence / "gt.txt"), "--out", str(out),
                 "--no-progress", "--no-video"]) == 0
    printed = capsys.readouterr().out
    result = torchtrack.track(frames=sequence / "frames", gt=sequence / "gt.txt", draw_video=False)
    np.testing.assert_allclose(result.tracks, _rows(out / "tracks.txt"), atol=6e-4)
    np.testing.assert_allclose(result.detections, _rows(out / "detections.txt"), atol=6e-4)
    written = json.loads((out / "metrics.json").read_text())
    assert {k: result.metrics[k] for k in written["clear_mot"]} == written["clear_mot"]
    # the printed table is in percent (MOTA %), as every other table
    assert "MOTA (%)" in printed and f"{100 * result.metrics['MOTA']:.2f}" in printed

    video = tmp_path / "in.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 2.0, (256, 256), False)
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in sorted((sequence / "frames").iterdir())]
    for image in images:
        writer.write(image)
    writer.release()
    from_video = torchtrack.track(video=video, gt=sequence / "gt.txt", draw_video=False)
    np.testing.assert_allclose(from_video.tracks, result.tracks, atol=6e-4)
    from_arrays = torchtrack.track(frames=np.stack(images), gt=sequence / "gt.txt", draw_video=False)
    np.testing.assert_allclose(from_arrays.tracks, result.tracks, atol=6e-4)

    # one flat shape for every input: the keys of eval --json, the tracker's extras beside them
    pred = tmp_path / "pred.txt"
    np.savetxt(pred, result.tracks, delimiter=",", fmt="%.6f")
    assert main(["eval", "--gt", str(sequence / "gt.txt"), "--pred", str(pred), "--moving", "--json",
                 str(tmp_path / "e.json")]) == 0
    evaluated = json.loads((tmp_path / "e.json").read_text())
    from_detections = torchtrack.track(detections=result.detections, gt=sequence / "gt.txt")
    keys = set(evaluated) | set(EXTRAS)
    assert set(result.metrics) == set(from_video.metrics) == set(from_detections.metrics) == keys
    assert result.metrics["MOTA"] == pytest.approx(evaluated["MOTA"], abs=1e-12)
    assert result.metrics["moving_only"] is evaluated["moving_only"] is True

def test_evaluate_equals_eval_json(tmp_path):
    gt, det = scene(tmp_path)
    tracks = torchtrack.track(detections=det, tracker="greedy").tracks
    pred = tmp_path / "pred.txt"
    np.savetxt(pred, tracks, delimiter=",", fmt="%.6f")
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), "--json", str(tmp_path / "e.json")]) == 0
    written = json.loads((tmp_path / "e.json").read_text())
    assert torchtrack.evaluate(gt, pred) == written
    assert torchtrack.evaluate(read_mot(gt), from_rows(tracks)) == pytest.approx(written)


def test_bad_input_is_one_error():
    with pytest.raises(TorchtrackError, match="exactly one input"):
        torchtrack.track()
    with pytest.raises(TorchtrackError, match=r"shape \(K, 6..10\)"):
        torchtrack.track(detections=np.zeros((3, 3)))
