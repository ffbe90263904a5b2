"""Every tracker run goes through one stream: detections -> gate -> tracker -> fixed lag -> recorder.

Checked against independent references: the recorder against what it was given and against its own file
read back; a detection file through the stream against stepping the tracker by hand; the moving-object gate
of a pipeline config against the speeds of what reached the tracker; the WPAFB benchmark (by preset name)
against ``track --detections`` on the detections it wrote (to the file's 3 decimals); Table 1's percentages by hand.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_baselines_track_cli import scene
from test_io_wpafb import write_csv

from torchtrack.cli import main
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.io.mot import read_mot
from torchtrack.metrics.table import TABLE1_HEADER, format_table1, table1_row
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.detection_file import detection_file_config
from torchtrack.pipeline.frame_detections import mot_frames, stream_frames
from torchtrack.pipeline.recorder import TrackRecorder
from torchtrack.pipeline.replay import run_tracker


def test_recorder_keeps_in_memory_what_it_writes_and_flushes_each_frame(tmp_path):
    rng = np.random.default_rng(0)
    given = [(k, rng.permutation(9)[: k + 1], rng.uniform(0, 500, (k + 1, 2))) for k in range(1, 6)]
    path = tmp_path / "tracks.txt"
    with TrackRecorder(path) as rec:
        for k, ids, pos in given:
            rec.record(k, ids, pos)
            assert read_mot(tmp_path / "tracks.partial.txt").frame.max() == k  # on disk as soon as recorded
            assert not path.exists()                                        # the final name: when complete
    tracks = rec.tracks()
    np.testing.assert_array_equal(tracks.frame, np.concatenate([np.full(len(i), k) for k, i, _ in given]))
    np.testing.assert_array_equal(tracks.id, np.concatenate([i for _, i, _ in given]))
    np.testing.assert_array_equal(tracks.centers(), np.concatenate([p for _, _, p in given]))  # exact, not rounded
    on_disk = read_mot(path)
    np.testing.assert_array_equal(on_disk.id, tracks.id)
    np.testing.assert_allclose(on_disk.centers(), tracks.centers(), atol=1e-3)   # the file keeps 3 decimals


@pytest.mark.parametrize("name", ["gmphd", "labelled-gmphd", "sort", "greedy"])
def test_detection_file_stream_equals_stepping_the_tracker_by_hand(tmp_path, name):
    gt_path, det_path = scene(tmp_path, seed=2)
    det = read_mot(det_path)
    frames = stream_frames(det, read_mot(gt_path))
    expected = []
    tracker = make_tracker(name, None)
    centres, velocity = det.centers(), det.velocity()
    for f in frames:
        idx = np.flatnonzero(det.frame == f)
        ids, pos = tracker.step(f, torch.from_numpy(centres[idx]), torch.from_numpy(velocity[idx]))
        expected += [(f, i, *p) for i, p in zip(ids.tolist(), pos.double().tolist())]
    run = run_tracker(make_tracker(name, None), detection_file_config(), mot_frames(det, frames))
    got = [(f, i, x, y) for f, i, (x, y) in zip(run.tracks.frame.tolist(), run.tracks.id.tolist(),
                                                run.tracks.centers().tolist())]
    assert len(expected) > 30 and run.frames == len(frames)
    assert [g[:2] for g in got] == [e[:2] for e in expected]
    np.testing.assert_allclose(np.array(got)[:, 2:], np.array(expected)[:, 2:], rtol=0, atol=1e-12)


class _Recording:
    """A stand-in tracker that reports nothing and records what it is given."""

    def __init__(self) -> None:
        self.given: list[tuple[np.ndarray, np.ndarray | None]] = []

    def step(self, frame, positions, velocities=None):
        self.given.append((positions.numpy(), None if velocities is None else velocities.numpy()))
        return torch.zeros(0, dtype=torch.int64), torch.zeros(0, 2, dtype=torch.float64)


def test_a_pipeline_config_gate_applies_to_a_detection_file(tmp_path):
    _, det_path = scene(tmp_path, seed=3)   # targets at 4.1, 3.6 and 4.0 px/frame, clutter at 0
    det = read_mot(det_path)
    speed = np.hypot(det.vx, det.vy)
    for base, reaching in ((None, det.size), (PipelineConfig(min_speed=2.0, output_lag=0), int((speed >= 2).sum()))):
        tracker = _Recording()
        run_tracker(tracker, detection_file_config(base=base), mot_frames(det, stream_frames(det)))
        given = np.concatenate([v for _, v in tracker.given])
        assert len(given) == reaching
        if base is not None:
            assert np.hypot(*given.T).min() >= 2.0


def test_benchmark_by_preset_name_scores_what_track_detections_scores(tmp_path, monkeypatch):
    frames = range(1, 31)
    rows = [(100 + k, (50 + 3 * k, 40 + 2 * k), (300 - 2 * k, 200 + 3 * k), (120, 400)) for k in frames]
    data = tmp_path / "wpafb"
    data.mkdir()
    write_csv(data / "transformed_object_states.csv", rows, ids=(1, 2, 3))
    monkeypatch.setenv("TORCHTRACK_WPAFB", str(data))
    monkeypatch.chdir(tmp_path)                       # no configs/ folder here: the preset comes with the package
    assert main(["track", "--benchmark", "wpafb", "--trackers", "sort", "greedy", "--out", "bench"]) == 0
    payload = json.loads((tmp_path / "bench" / "benchmark.json").read_text())
    assert set(payload["subsets"]) == {"all", "moving"}
    for subset in ("all", "moving"):
        folder = tmp_path / "bench" / subset
        assert main(["track", "--detections", str(folder / "det.txt"), "--gt", str(folder / "gt.txt"),
                     "--tracker", "sort", "--config", "gmphd", "--score", subset,
                     "--out", str(tmp_path / "alone")]) == 0
        alone = json.loads((tmp_path / "alone" / "metrics.json").read_text())
        bench = payload["subsets"][subset]["sort"]
        assert {k: alone[k] for k in ("MOTA", "IDS", "FP", "FN")} == {k: bench[k] for k in ("MOTA", "IDS", "FP", "FN")}
        for key in ("MOTP", "HOTA", "IDF1"):                            # det.txt keeps 3 decimals
            assert alone[key] == pytest.approx(bench[key], abs=1e-3), key


def test_table1_rows_by_hand():
    m = {"GT": 8, "MT": 2, "PT": 5, "ML": 1, "FP": 3, "FN": 4, "IDS": 1, "MOTA": 0.5, "HOTA": 0.25, "IDF1": 0.75,
         "MOTP": 1.25, "FPS": 10.0}
    assert table1_row("x", m) == ["x", 8, 25.0, 62.5, 12.5, 3, 4, 1, 50.0, 25.0, 75.0, 1.25, 10.0]
    empty = {**m, "GT": 0, "MT": 0, "PT": 0, "ML": 0}
    assert table1_row("y", empty)[2:5] == [0.0, 0.0, 0.0]           # no trajectories: 0 %, not NaN
    text = format_table1({"x": m, "y": empty}, "title").splitlines()[1:]
    assert all(h in text[0] for h in TABLE1_HEADER)
    assert text[2].split() == ["x", "8", "25.00", "62.50", "12.50", "3", "4", "1", "50.00", "25.00", "75.00", "1.25",
                               "10.00"]
