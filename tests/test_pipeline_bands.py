"""Whole-frame OpenCV steps of the pipeline computed over bands of rows (issue #28 memory) give the whole frame's
results: the registration's corners (``goodFeaturesToTrack``), the motion evidence and grey levels (box filters)."""

import cv2
import numpy as np
import pytest
import torch

from torchtrack.pipeline import corners, detection
from torchtrack.pipeline.corners import good_features
from torchtrack.pipeline.detection import grey_level, motion_evidence
from torchtrack.sim.video import generate_sequence
from torchtrack.sim.video_config import VideoConfig


@pytest.fixture(scope="module")
def frame():
    config = VideoConfig(height=700, width=520, frames=1)
    return next(iter(generate_sequence(config, torch.Generator().manual_seed(4)))).image


@pytest.mark.parametrize("count", [5000, 300])
def test_bands_give_opencvs_corners_in_opencvs_order(frame, count, monkeypatch):
    monkeypatch.setattr(corners, "BAND_ROWS", 96)                 # 8 bands, one of them short
    ref = cv2.goodFeaturesToTrack(frame, count, 0.01, 8, blockSize=7)
    got = good_features(frame, count, 0.01, 8, 7)
    assert len(ref) > 250 and (len(ref) == count) == (count == 300)
    np.testing.assert_array_equal(got, ref)


def test_a_flat_frame_has_no_corners():
    got = good_features(np.full((40, 50), 7, np.uint8), 10, 0.01, 8, 7)
    assert got.shape == (0, 1, 2) and got.dtype == np.float32


@pytest.mark.parametrize("count", [1000, 50])
def test_equal_eigenvalues_keep_opencvs_order(count, monkeypatch):
    """Identical squares on a flat ground: every corner has the same eigenvalue; OpenCV takes the later pixel
    in raster order first, and the cut at ``count`` falls among them."""
    monkeypatch.setattr(corners, "BAND_ROWS", 64)
    image = np.full((300, 260), 50, np.uint8)
    for y in range(20, 280, 37):
        for x in range(15, 240, 29):
            image[y:y + 6, x:x + 6] = 200
    ref = cv2.goodFeaturesToTrack(image, count, 0.01, 8, blockSize=7)
    eig = cv2.cornerMinEigenVal(image, 7, ksize=3)
    assert len(np.unique(eig[ref[:, 0, 1].astype(int), ref[:, 0, 0].astype(int)])) == 1
    np.testing.assert_array_equal(good_features(image, count, 0.01, 8, 7), ref)


def test_banded_motion_evidence_and_grey_levels_are_the_whole_frames(frame, monkeypatch):
    monkeypatch.setattr(detection, "BAND_ROWS", 7)
    previous = np.roll(frame, (2, -3), axis=(0, 1))
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-3, [523, 703], (3000, 2)), [[0, 0], [519, 699], [5, 6.5], [5, 7.4]]])
    x = np.clip(np.rint(points[:, 0]).astype(int), 0, 519)
    y = np.clip(np.rint(points[:, 1]).astype(int), 0, 699)
    motion = cv2.blur(cv2.absdiff(frame, previous), (5, 5))[y, x]
    assert motion.max() > 20
    np.testing.assert_array_equal(motion_evidence(frame, previous, points), motion.astype(np.float64))
    np.testing.assert_array_equal(grey_level(frame, points), cv2.blur(frame, (3, 3))[y, x].astype(np.float64))
