"""A real camera in the pipeline: tracks restart at a new registration segment, new tracks beside older ones
are left out on cluttered video, and the moving-object gate allows for the registration's residual."""

import subprocess
import sys
from types import SimpleNamespace

import cv2
import numpy as np
import torch

from tests.test_registration_homography import _texture
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.detection import Detection, misregistration, motion_evidence
from torchtrack.pipeline.fixed_lag import FixedLagTracks
from torchtrack.pipeline.frame_detections import FrameDetections
from torchtrack.pipeline.registration import Registration, RegistrationConfig
from torchtrack.pipeline.timer import StageTimer
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


def _merge_run(tracks, lag=3, merge=6.0, cluttered=(1,), age=10):
    """``tracks``: {id: [(frame, x, y)]}, each position also a detection; the gate raised on the frames
    ``cluttered``; returns {frame: set(ids)}."""
    out = FixedLagTracks(lag=lag, distance=3.0, merge_distance=merge, merge_age=age)
    frames = sorted({f for pts in tracks.values() for f, _, _ in pts})
    got = []
    for k in frames:
        here = [(i, (x, y)) for i, pts in tracks.items() for f, x, y in pts if f == k]
        ids = np.array([i for i, _ in here])
        pos = np.array([p for _, p in here], float).reshape(-1, 2)
        got += out.push(k, ids, pos, pos, np.zeros_like(pos), k in cluttered)
    got += out.finish()
    return {f.index: set(f.ids.tolist()) for f in got}


def test_a_new_track_beside_an_older_one_on_cluttered_video_is_left_out():
    # Track 7 follows a vehicle from frame 1; track 9 appears on the same vehicle 3 px away from frame 3.
    tracks = {7: [(k, 10 + 4 * k, 50) for k in range(1, 21)], 9: [(k, 10 + 4 * k, 53) for k in range(3, 21)]}
    out = _merge_run(tracks, cluttered=range(1, 21), age=5)
    assert all(out[k] == {7} for k in range(1, 8))                     # 9 younger than 5 frames: left out
    assert all(out[k] == {7, 9} for k in range(8, 21))                 # then established: kept
    out = _merge_run(tracks, cluttered=(1,), age=5)                     # the gate raised on frame 1 only
    assert all(out[k] == {7} for k in range(1, 7)) and out[7] == {7, 9}  # frame 7 is 6 frames after it
    assert _merge_run(tracks, merge=0.0)[5] == {7, 9}                   # off: both kept
    assert _merge_run(tracks, cluttered=())[5] == {7, 9}                # clean video: vehicles meeting, both kept
    assert _merge_run(tracks, cluttered=(1,), age=1)[3] == {7, 9}        # the clutter too long ago


def test_tracks_apart_are_both_kept_on_cluttered_video():
    # Side by side 8 px apart for the whole run: two vehicles.
    tracks = {1: [(k, 10 + 4 * k, 50) for k in range(1, 11)], 2: [(k, 10 + 4 * k, 58) for k in range(3, 11)]}
    assert all(ids == ({1, 2} if k >= 3 else {1}) for k, ids in _merge_run(tracks, cluttered=range(1, 11)).items())


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
    det = _frame(2, 0, [[10.0, 10.0], [40.0, 40.0]])._replace(motion=np.array([8.0, 8.0]), clutter=np.array([4.5, 1.0]))
    assert len(det.moving(0.0, 5.0, 1.0).scores) == 1          # needs 5 + (4.5 - 1) = 8.5 > 8
    assert len(det.moving(0.0, 5.0, 0.0).scores) == 2


def test_gate_margin_ignores_a_difference_below_one_grey_level():
    # Motion evidence is whole grey levels: a detection at exactly min_motion is not refused for 0.9 of a level.
    det = _frame(2, 0, [[10.0, 10.0], [40.0, 40.0]])._replace(motion=np.array([5.0, 5.0]), clutter=np.array([0.9, 1.2]))
    assert det.moving(0.0, 5.0, 1.0).positions.tolist() == [[10.0, 10.0]]


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


class FixedPoints:
    """Two detections per frame, moving 3 px/frame."""

    def detect(self, frame, prev_frame, prev_points):
        return SimpleNamespace(xy=torch.tensor([[40.0, 40.0], [80.0, 90.0]]), score=torch.ones(2),
                               velocity=torch.tensor([[3.0, 0.0], [3.0, 0.0]]))


def test_gate_is_raised_only_on_frames_where_the_plain_gate_passes_more_than_its_budget():
    base = cv2.GaussianBlur(_texture((128, 128), 4), (0, 0), 1.0)
    noisy = np.clip(base.astype(int) + np.random.default_rng(0).integers(-2, 3, base.shape), 0, 255).astype(np.uint8)
    shifted = cv2.warpAffine(base, np.float32([[1, 0, 0.8], [0, 1, 0.0]]), (128, 128))  # a 0.8 px misregistration
    detection = Detection(FixedPoints(), Registration(RegistrationConfig(method="none")), StageTimer(),
                          gate=(5.0, 3.0, 2.0, 0.05, 0.0))
    assert not detection(1, base).cluttered                    # no previous frame
    clean = detection(2, noisy)                                 # sensor noise only: a few % pass
    assert detection.gate_pass <= 0.05 and not clean.cluttered and not clean.clutter.any()
    moved = detection(3, shifted)
    assert moved.cluttered
