"""A real camera in the pipeline: tracks restart at a new registration segment, duplicate tracks on one
vehicle are merged, and the moving-object gate allows for the registration's residual."""

import subprocess
import sys

import cv2
import numpy as np
import torch

from tests.test_registration_homography import _texture
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.detection import misregistration, motion_evidence
from torchtrack.pipeline.fixed_lag import FixedLagTracks
from torchtrack.pipeline.frame_detections import FrameDetections
from torchtrack.pipeline.tracker_stream import TrackerStream


class CountingTracker:
    """One identity per detection slot (1, 2, …), the same every frame; counts its resets."""

    def __init__(self):
        self.resets = 0

    def step(self, frame_index, positions, velocities):
        return torch.arange(1, len(positions) + 1), positions

    def reset(self):
        self.resets += 1


def _frame(index, segment, points):
    det = FrameDetections.registered(index, np.asarray(points, float), np.tile([4.0, 0.0], (len(points), 1)))
    return det._replace(segment=segment)


def test_a_new_segment_restarts_the_tracks_with_new_identities():
    tracker = CountingTracker()
    stream = TrackerStream(tracker, PipelineConfig(min_speed=0.0, min_motion=0.0, output_lag=2))
    final = []
    for k in range(1, 9):
        segment = 0 if k <= 4 else 1
        final += stream.step(_frame(k, segment, [[10.0 + 4 * k, 20.0], [10.0 + 4 * k, 80.0]]))[2]
    final += stream.finish()
    assert tracker.resets == 1
    assert [f.index for f in final] == list(range(1, 9))          # every frame once, in order
    before = {int(i) for f in final[:4] for i in f.ids}
    after = {int(i) for f in final[4:] for i in f.ids}
    assert before == {1, 2} and len(after) == 2 and min(after) > max(before)  # identities never reused


def _merge_run(tracks, lag=3, merge=6.0):
    """``tracks``: {id: [(frame, x, y)]}, each position also a detection; returns {frame: set(ids)}."""
    out = FixedLagTracks(lag=lag, distance=3.0, merge_distance=merge)
    frames = sorted({f for pts in tracks.values() for f, _, _ in pts})
    got = []
    for k in frames:
        here = [(i, (x, y)) for i, pts in tracks.items() for f, x, y in pts if f == k]
        ids = np.array([i for i, _ in here])
        pos = np.array([p for _, p in here], float).reshape(-1, 2)
        got += out.push(k, ids, pos, pos, np.zeros_like(pos))
    got += out.finish()
    return {f.index: set(f.ids.tolist()) for f in got}


def test_two_tracks_on_one_vehicle_become_one():
    # Track 7 follows a vehicle from frame 1; track 9 appears on the same vehicle 3 px away from frame 3.
    tracks = {7: [(k, 10 + 4 * k, 50) for k in range(1, 11)], 9: [(k, 10 + 4 * k, 53) for k in range(3, 11)]}
    out = _merge_run(tracks)
    assert all(ids == {7} for ids in out.values())
    assert _merge_run(tracks, merge=0.0)[5] == {7, 9}                   # off: both kept


def test_vehicles_that_only_pass_each_other_are_both_kept():
    # Opposite directions: 3 px apart at frame 5 only.
    tracks = {1: [(k, 10 + 4 * k, 50) for k in range(1, 11)], 2: [(k, 70 - 4 * k + 0.0, 53) for k in range(1, 11)]}
    out = _merge_run(tracks)
    assert all(ids == {1, 2} for ids in out.values())
    # Side by side 8 px apart for the whole run: two vehicles.
    tracks = {1: [(k, 10 + 4 * k, 50) for k in range(1, 11)], 2: [(k, 10 + 4 * k, 58) for k in range(1, 11)]}
    assert all(ids == {1, 2} for ids in _merge_run(tracks).values())


def test_gate_margin_bounds_the_difference_of_a_misregistration():
    image = cv2.GaussianBlur(_texture((128, 128), 2), (0, 0), 1.5)
    for dx, dy in [(0.3, 0.0), (0.0, 0.3), (0.2, 0.2)]:
        shifted = cv2.warpAffine(image, np.float32([[1, 0, dx], [0, 1, dy]]), (128, 128), flags=cv2.INTER_LINEAR)
        pts = np.stack(np.meshgrid(np.arange(16, 112, 8), np.arange(16, 112, 8)), -1).reshape(-1, 2).astype(float)
        measured = motion_evidence(image, shifted, pts)
        bound = misregistration(image, shifted, float(np.hypot(dx, dy)), pts)
        assert np.mean(measured <= bound + 1.0) > 0.95          # the first-order bound (1 grey level of rounding)
        assert np.median(measured) > 0.4 * np.median(bound)     # and not a loose one


def test_gate_margin_removes_a_detection_explained_by_the_residual():
    det = _frame(2, 0, [[10.0, 10.0], [40.0, 40.0]])._replace(motion=np.array([8.0, 8.0]), clutter=np.array([4.0, 1.0]))
    assert len(det.moving(0.0, 5.0, 1.0).scores) == 1
    assert len(det.moving(0.0, 5.0, 0.0).scores) == 2


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "torchtrack", *args], capture_output=True, text=True, timeout=120)


def test_bad_frame_folders_are_one_line_errors(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    r = _cli("track", "--frames", str(empty), "--out", str(tmp_path / "o1"), "--no-progress")
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0
    assert r.stderr.startswith("torchtrack track: error:") and "empty" in r.stderr
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    cv2.imwrite(str(mixed / "1.png"), _texture((64, 64), 1))
    cv2.imwrite(str(mixed / "2.png"), _texture((48, 64), 1))
    r = _cli("track", "--frames", str(mixed), "--out", str(tmp_path / "o2"), "--no-progress", "--no-video")
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0
    assert r.stderr.startswith("torchtrack track: error:") and "2.png" in r.stderr
    assert not (tmp_path / "o2").exists()
