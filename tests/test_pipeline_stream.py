"""Pipeline plumbing with test-only stand-ins for the detector and the tracker: coordinates through
registration, per-frame flushing, interruption, and the artefacts written."""

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from torchtrack.geometry import apply_homography, homography_jacobian
from torchtrack.io.frames import ArraySource
from torchtrack.io.mot import read_mot
from torchtrack.pipeline import track_video as tv
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.detection import motion_evidence
from torchtrack.sim.video import VideoConfig, generate_sequence
from torchtrack.threads import TRACKER_THREADS, available_cores, torch_threads


@pytest.fixture(scope="module")
def sequence():
    cfg = VideoConfig(height=160, width=160, frames=5)
    return list(generate_sequence(cfg, torch.Generator().manual_seed(3)))


class OracleDetector:
    """Returns the true positions of the frame it is given (looked up by image identity)."""

    def __init__(self, sequence, stop_at=None):
        self.by_id = {id(f.image): f for f in sequence}
        self.calls = []
        self.stop_at = stop_at

    def detect(self, frame, prev_frame, prev_points):
        truth = self.by_id[id(frame)]
        self.calls.append((frame, prev_frame, np.asarray(prev_points)))
        if self.stop_at is not None and len(self.calls) == self.stop_at:
            raise KeyboardInterrupt
        n = len(truth.xy)
        return SimpleNamespace(xy=torch.tensor(truth.xy), score=torch.ones(n), velocity=torch.zeros(n, 2))


class RecordingTracker:
    """Gives each detection of frame k the id 1000 k + j and records the reference positions it saw."""

    def __init__(self):
        self.seen = []

    def step(self, frame_index, positions, velocities):
        self.seen.append(positions.clone())
        ids = 1000 * frame_index + torch.arange(len(positions))
        return ids, positions

    def reset(self):
        self.seen.clear()


def _run(tmp_path, sequence, monkeypatch, detector, **cfg):
    tracker = RecordingTracker()
    monkeypatch.setattr(tv, "make_tracker", lambda name, options: tracker)
    source = ArraySource([f.image for f in sequence])
    # ArraySource converts with np.asarray (no copy for uint8 grey), so the oracle finds its frames.
    cfg = {"min_speed": 0.0, "min_motion": 0.0, "merge_distance": 0.0, **cfg}  # stand-ins: no velocity, no gate;
    # the oracle reports every vehicle, neighbours a few px apart included: no merging either
    result = tv.track_video(source, tmp_path, PipelineConfig(**cfg), detector=detector, progress=False,
                            camera=np.stack([f.homography for f in sequence]))
    return result, tracker


def test_positions_reach_the_tracker_in_reference_coordinates(tmp_path, sequence, monkeypatch):
    result, tracker = _run(tmp_path, sequence, monkeypatch, OracleDetector(sequence))
    h1 = sequence[0].homography
    for f, seen in zip(sequence, tracker.seen):
        # Truth in frame k mapped to frame 1 by the TRUE camera motion H_1 H_k^{-1}.
        expected = apply_homography(f.xy, h1 @ np.linalg.inv(f.homography))
        err = np.linalg.norm(seen.numpy() - expected, axis=1)
        assert np.median(err) < 0.5 and err.max() < 1.0  # registration of a tiny 160 x 160 frame
    # tracks.txt is in frame coordinates again: the truth of each frame, exactly.
    tracks = read_mot(result.files["tracks"])
    for f, idx in zip(sequence, tracks.split(range(1, 6))):
        np.testing.assert_allclose(tracks.centers()[idx], f.xy, atol=2e-3)
    m = json.loads(result.files["metrics"].read_text())
    assert m["frames"] == 5 and m["registration_error_px"]["median"] < 0.5
    # The registration's own account: one segment, a small frame-to-frame residual, a line per frame.
    reg = m["registration"]
    assert reg["segments"] == 1 and reg["residual_px"]["frames"] == 4 and reg["residual_px"]["median"] < 0.3
    lines = result.files["registration"].read_text().splitlines()
    assert lines[0].startswith("frame,residual_px") and [int(x.split(",")[0]) for x in lines[1:]] == [1, 2, 3, 4, 5]
    assert {"registration", "detection", "tracking", "io", "render"} <= set(m["timings_s"])
    assert m["fps"]["end_to_end"] > 0
    assert (tmp_path / "frame_000001.png").exists()


def test_detector_sees_registered_previous_frame_and_prior(tmp_path, sequence, monkeypatch):
    det = OracleDetector(sequence)
    _run(tmp_path, sequence, monkeypatch, det)
    frame, prev, prior = det.calls[3]
    # The previous frame, warped into this one, lines up with it (only vehicles and noise differ).
    raw_diff = np.median(np.abs(frame.astype(float) - sequence[2].image.astype(float)))
    reg_diff = np.median(np.abs(frame.astype(float) - prev.astype(float))[8:-8, 8:-8])
    assert reg_diff < raw_diff
    # The prior points are the previous frame's detections, mapped into this frame.
    expected = apply_homography(sequence[2].xy, sequence[3].homography @ np.linalg.inv(sequence[2].homography))
    err = np.linalg.norm(prior - expected, axis=1)
    assert np.median(err) < 0.5 and err.max() < 1.0


@pytest.mark.parametrize("lag", [0, 1, 2])
def test_interrupted_run_leaves_consistent_tracks(tmp_path, sequence, monkeypatch, lag):
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path, sequence, monkeypatch, OracleDetector(sequence, stop_at=4), output_lag=lag)
    # Frames 1-3 were completed; with an output lag L only frames 1..3-L were final.
    final = tuple(range(1, 4 - lag))
    assert not (tmp_path / "tracks.txt").exists()  # the final name only ever holds a whole run
    tracks = read_mot(tmp_path / "tracks.partial.txt")
    assert set(tracks.frames().tolist()) == set(final)
    for k, idx in zip(final, tracks.split(final)):
        assert len(idx) == len(sequence[k - 1].xy)
    assert not (tmp_path / "metrics.json").exists()
    assert not (tmp_path / "annotated.mp4").exists() and (tmp_path / "annotated.partial.mp4").exists()


def test_annotated_video_decodes(tmp_path, sequence, monkeypatch):
    result, _ = _run(tmp_path, sequence, monkeypatch, OracleDetector(sequence), scale=2)
    cap = cv2.VideoCapture(str(result.files["video"]))
    n = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        assert img.shape[1:] == (320, 3) and img.shape[0] > 320  # scaled twice, the legend band below
        n += 1
    assert n == 5


def test_homography_jacobian_matches_finite_differences():
    h = np.array([[1.01, 0.02, 3.0], [-0.01, 0.99, -2.0], [1e-4, -2e-4, 1.0]])
    p = np.array([[10.0, 20.0], [100.0, 50.0]])
    eps = 1e-5
    num = np.stack([(apply_homography(p + eps * e, h) - apply_homography(p - eps * e, h)) / (2 * eps)
                    for e in np.eye(2)], axis=2)
    np.testing.assert_allclose(homography_jacobian(h, p), num, rtol=1e-7, atol=1e-9)


class OnePoint:
    def detect(self, frame, prev_frame, prev_points):
        return SimpleNamespace(xy=torch.tensor([[40.0, 50.0]]), score=torch.ones(1), velocity=torch.zeros(1, 2))


def test_size_change_mid_run_names_the_file_and_leaves_no_complete_results(tmp_path, sequence, monkeypatch):
    frames = tmp_path / "frames"
    frames.mkdir()
    for k, f in enumerate(sequence[:4], start=1):
        image = f.image if k != 3 else f.image[:100]
        cv2.imwrite(str(frames / f"{k:03d}.png"), image)
    monkeypatch.setattr(tv, "make_tracker", lambda name, options: RecordingTracker())
    from torchtrack.errors import TorchtrackError
    from torchtrack.io.frames import FolderSource

    out = tmp_path / "out"
    (out).mkdir()
    (out / "metrics.json").write_text("{}")  # a previous run's result must not survive beside the new files
    with pytest.raises(TorchtrackError, match=r"003\.png: frame size 160x100 differs from 160x160"):
        tv.track_video(FolderSource(frames), out, PipelineConfig(min_speed=0.0, min_motion=0.0, output_lag=1),
                       detector=OnePoint(), progress=False)
    assert not (out / "metrics.json").exists() and not (out / "annotated.mp4").exists()
    assert not (out / "tracks.txt").exists()  # no short file under the final name: the partial one
    assert read_mot(out / "tracks.partial.txt").frames().tolist() == [1]  # complete up to the last final frame


def test_truth_beyond_the_frames_is_refused_before_writing(tmp_path, sequence, monkeypatch):
    from torchtrack.errors import TorchtrackError
    from torchtrack.io.mot import from_points

    monkeypatch.setattr(tv, "make_tracker", lambda name, options: RecordingTracker())
    gt = from_points([1, 2, 7], [1, 1, 1], [10, 11, 12], [10, 10, 10])
    with pytest.raises(TorchtrackError, match=r"my_gt\.txt: truth refers to frames up to 7, but the video has only 5"):
        tv.track_video(ArraySource([f.image for f in sequence]), tmp_path, PipelineConfig(), detector=OnePoint(),
                       gt=gt, gt_path="my_gt.txt", progress=False)
    assert not (tmp_path / "tracks.txt").exists() and not (tmp_path / "metrics.json").exists()


class RepeatingTracker(RecordingTracker):
    """Breaks the contract: reports identity 5 twice in every frame."""

    def step(self, frame_index, positions, velocities):
        return torch.tensor([5, 6, 5]), torch.tensor([[1.0, 2.0], [3.0, 4.0], [9.0, 9.0]], dtype=torch.float64)


def test_repeated_identity_is_dropped_counted_and_warned(tmp_path, sequence, monkeypatch):
    monkeypatch.setattr(tv, "make_tracker", lambda name, options: RepeatingTracker())
    with pytest.warns(UserWarning, match="5 estimate"):
        result = tv.track_video(ArraySource([f.image for f in sequence]), tmp_path,
                                PipelineConfig(video=False, output_lag=0), detector=OnePoint(), progress=False)
    tracks = read_mot(result.files["tracks"])  # a valid file: one line per (frame, id)
    assert tracks.size == 10 and set(tracks.id.tolist()) == {5, 6}
    assert result.metrics["duplicate_identities_dropped"] == 5


class TwoSpeeds:
    """Two detections per frame: one at rest, one moving at 3 px/frame."""

    def detect(self, frame, prev_frame, prev_points):
        return SimpleNamespace(xy=torch.tensor([[40.0, 40.0], [80.0, 90.0]]), score=torch.ones(2),
                               velocity=torch.tensor([[0.0, 0.0], [3.0, 0.0]]))


def test_min_speed_keeps_slow_detections_from_the_tracker_only(tmp_path, sequence, monkeypatch):
    result, tracker = _run(tmp_path, sequence, monkeypatch, TwoSpeeds(), min_speed=2.0, video=False)
    assert [len(seen) for seen in tracker.seen] == [2, 1, 1, 1, 1]  # frame 1: no previous frame, speed unknown
    assert read_mot(result.files["detections"]).size == 10  # the detector's output is recorded whole


def test_pipeline_tracker_options_per_name():
    cfg = PipelineConfig(tracker="sort", trackers={"sort": {"max_age": 3}, "greedy": {"max_distance": 5.0}},
                         tracker_options={"max_age": 7})
    assert cfg.options_for("sort") == {"max_age": 7}
    assert cfg.options_for("greedy") == {"max_distance": 5.0}
    assert cfg.options_for("gmphd") is None


def test_motion_evidence_is_the_local_frame_difference():
    previous = np.full((40, 40), 60, np.uint8)
    image = previous.copy()
    image[18:23, 28:33] = 160  # a 5 x 5 vehicle arrived; nothing else changed
    ev = motion_evidence(image, previous, np.array([[30.0, 20.0], [10.0, 10.0], [32.0, 20.0]]))
    np.testing.assert_allclose(ev, [100.0, 0.0, 60.0])  # centred: all 25 px differ; 2 px off: 15 of 25


class ScoredPeaks:
    """A strong and a weak detection per frame, decoded down to ``threshold``; records the priors it gets."""

    config = SimpleNamespace(decode=SimpleNamespace(threshold=0.5))

    def __init__(self):
        self.priors = []

    def detect(self, frame, prev_frame, prev_points, threshold=0.5):
        self.priors.append(np.asarray(prev_points))
        xy, score = torch.tensor([[40.0, 40.0], [80.0, 90.0]]), torch.tensor([0.9, 0.2])
        keep = score >= threshold
        return SimpleNamespace(xy=xy[keep], score=score[keep], velocity=torch.zeros(int(keep.sum()), 2))


def test_detection_threshold_feeds_the_tracker_but_not_the_prior(tmp_path, sequence, monkeypatch):
    detector = ScoredPeaks()
    _, tracker = _run(tmp_path, sequence, monkeypatch, detector, detection_threshold=0.1, video=False)
    assert [len(seen) for seen in tracker.seen] == [2] * 5
    assert [len(p) for p in detector.priors] == [0, 1, 1, 1, 1]  # only the strong peak becomes the prior


@pytest.mark.skipif(available_cores() < 2, reason="needs two cores to tell two threads from one")
def test_the_detector_runs_on_the_configured_threads_the_tracker_on_one(tmp_path, sequence, monkeypatch):
    class CountingDetector(OracleDetector):
        def detect(self, frame, prev_frame, prev_points):
            self.threads = {*getattr(self, "threads", set()), torch.get_num_threads()}
            return super().detect(frame, prev_frame, prev_points)

    class CountingTracker(RecordingTracker):
        threads: set = set()

        def step(self, frame_index, positions, velocities):
            CountingTracker.threads = {*CountingTracker.threads, torch.get_num_threads()}
            return super().step(frame_index, positions, velocities)

    detector, before = CountingDetector(sequence), torch.get_num_threads()
    tracker = CountingTracker()
    monkeypatch.setattr(tv, "make_tracker", lambda name, options: tracker)
    cfg = PipelineConfig(min_speed=0.0, min_motion=0.0, merge_distance=0.0, threads=2, video=False)
    tv.track_video(ArraySource([f.image for f in sequence]), tmp_path, cfg, detector=detector, progress=False)
    assert detector.threads == {2} and CountingTracker.threads == {TRACKER_THREADS} == {1}
    assert torch.get_num_threads() == before                     # restored after the run


def test_the_filters_benches_default_to_the_trackers_threads():
    from torchtrack.bench import kf

    with torch_threads(min(2, available_cores())):
        result = kf.measure(tracks=64, steps=2, general_steps=2, loop_tracks=2, compile=False)
    assert result.extra["threads"] == TRACKER_THREADS
