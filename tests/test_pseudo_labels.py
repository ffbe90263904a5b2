"""Pseudo-labels from the pipeline's confident tracks, checked against a synthetic video's truth."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from torchtrack.detector import load_detector
from torchtrack.io.frames import FolderSource
from torchtrack.io.mot import from_points, read_mot
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.pseudo_labels import confident_tracks, frame_motions, pseudo_labels
from torchtrack.pipeline.track_video import track_video
from torchtrack.sim.video import VideoConfig, write_sequence


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("pseudo")
    seq = write_sequence(VideoConfig(height=256, width=256, frames=24), torch.Generator().manual_seed(11),
                         root / "seq")
    result = track_video(FolderSource(seq / "frames"), root / "out", PipelineConfig(video=False),
                         detector=load_detector(None), keep_detections=True, progress=False)
    frames = np.stack([f.image for f in FolderSource(seq / "frames")])
    return frames, result, read_mot(seq / "gt.txt")


def _precision(points_by_frame, gt):
    hits = total = 0
    for k, pts in enumerate(points_by_frame, start=1):
        truth = gt.centers()[gt.frame == k]
        if len(pts):
            hits += int((cKDTree(truth).query(pts)[0] < 3.0).sum())
            total += len(pts)
    return hits / max(total, 1), total


def test_confident_pseudo_labels_are_vehicles(run):
    frames, result, gt = run
    labels = pseudo_labels(frames, result.tracks, [d.homography for d in result.detections], min_length=8)
    precision, count = _precision(labels.xy, gt)
    every = [result.tracks.centers()[result.tracks.frame == k] for k in range(1, len(frames) + 1)]
    all_precision, all_count = _precision(every, gt)
    assert count >= 50 and count < all_count
    assert precision >= 0.95 and precision >= all_precision
    # velocities linked by identity: image motion of the vehicle under them
    v = np.concatenate([x for x in labels.velocity[1:]])
    assert np.isfinite(v).mean() > 0.8 and np.nanmedian(np.hypot(*v.T)) > 1.0


def test_confident_tracks_keep_long_identities_only():
    t = from_points([1, 2, 3, 1, 2], [7, 7, 7, 9, 9], [1.0, 2, 3, 5, 6], [1.0, 1, 1, 5, 5])
    assert confident_tracks(t, 3).id.tolist() == [7, 7, 7]


def test_frame_motions_map_current_to_previous():
    h1 = np.array([[1, 0, 5.0], [0, 1, -2], [0, 0, 1]])
    h2 = np.array([[1, 0, 8.0], [0, 1, 1], [0, 0, 1]])
    m = frame_motions([np.eye(3), h1, h2])
    x = np.array([10.0, 20.0, 1.0])
    assert np.allclose(m[0], np.eye(3)) and np.allclose(h1 @ (m[2] @ x), h2 @ x)
