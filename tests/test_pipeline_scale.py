"""``vehicle_length``: the detector sees frames resampled to its training scale, and its detections come back in
the frame's pixels (checked with a detector that finds blob centroids, against where the blobs were drawn)."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from torchtrack.pipeline.config import TRAINED_VEHICLE_LENGTH, PipelineConfig
from torchtrack.pipeline.detection import Detection
from torchtrack.pipeline.registration import Registration, RegistrationConfig
from torchtrack.pipeline.timer import StageTimer

CENTRES = np.array([[20.3, 30.7], [61.6, 18.2], [45.1, 70.9], [90.4, 88.8]])


def _frame(sigma: float) -> np.ndarray:
    ys, xs = np.mgrid[0:112, 0:128]
    img = np.full((112, 128), 40.0)
    for x, y in CENTRES:
        img += 180 * np.exp(-((xs - x) ** 2 + (ys - y) ** 2) / (2 * sigma**2))
    return np.clip(img, 0, 255).astype(np.uint8)


class CentroidDetector:
    """Intensity-weighted centroids of the bright blobs of the frame it is given; records what it saw."""

    def __init__(self):
        self.seen = []

    def detect(self, frame, prev_frame, prev_points):
        self.seen.append((frame.shape, np.asarray(prev_points)))
        _, labels = cv2.connectedComponents((frame > 42).astype(np.uint8))  # the blobs with their tails
        w = frame.astype(np.float64) - 40
        xy = [[(w * xs).sum() / w[m].sum(), (w * ys).sum() / w[m].sum()]
              for k in range(1, labels.max() + 1)
              for m in [labels == k] for ys, xs in [np.where(m, np.mgrid[0:frame.shape[0], 0:frame.shape[1]], 0)]]
        xy = torch.tensor(xy, dtype=torch.float64).reshape(-1, 2)
        return SimpleNamespace(xy=xy, score=torch.ones(len(xy)), velocity=torch.full((len(xy), 2), 0.5))


@pytest.mark.parametrize("length", [2.5, 10.0])
def test_detections_come_back_in_the_frames_pixels(length):
    config = PipelineConfig(vehicle_length=length)
    scale = config.detector_scale
    assert scale == pytest.approx(TRAINED_VEHICLE_LENGTH / length)
    detector = CentroidDetector()
    detection = Detection(detector, Registration(RegistrationConfig(method="none")), StageTimer(), scale=scale)
    frame = _frame(sigma=2.0)
    first = detection(1, frame)
    second = detection(2, frame)
    assert detector.seen[0][0] == (round(112 * scale), round(128 * scale))        # resampled for the detector
    order = np.argsort(first.image_positions[:, 0])
    np.testing.assert_allclose(first.image_positions[order], CENTRES[np.argsort(CENTRES[:, 0])], atol=0.1)
    np.testing.assert_allclose(first.image_velocities, 0.5 / scale)               # px/frame of the frame
    # The prior of frame 2 (frame 1's detections) reaches the detector in its resampled pixels.
    np.testing.assert_allclose(np.sort(detector.seen[1][1][:, 0]),
                               np.sort((first.image_positions[:, 0] + 0.5) * scale - 0.5), atol=1e-9)
    assert len(second.scores) == len(CENTRES)


def test_no_vehicle_length_leaves_the_frames_alone():
    assert PipelineConfig().detector_scale == 1.0
    with pytest.raises(Exception, match="vehicle_length"):
        PipelineConfig(vehicle_length=0.0)
