"""The moving-object gate relative to the frame's noise: ``frame_noise`` against the closed form for white noise,
and ``FrameDetections.moving`` with ``noise_factor`` against the rule written out."""

import numpy as np
import pytest

from torchtrack.pipeline.detection import frame_noise
from torchtrack.pipeline.frame_detections import FrameDetections


@pytest.mark.parametrize("sigma", [2.0, 6.0])
def test_frame_noise_is_the_median_absolute_difference_of_white_noise(sigma):
    rng = np.random.default_rng(0)
    a, b = (np.clip(np.rint(100 + sigma * rng.standard_normal((512, 512))), 0, 255).astype(np.uint8)
            for _ in range(2))
    # |N(0, 2σ²)| has median 0.6745 √2 σ; the difference of two rounded frames is a whole number of grey levels
    assert frame_noise(a, b) == pytest.approx(0.6745 * np.sqrt(2) * sigma, abs=0.75)
    moving = a.copy()
    moving[:40, :40] = 250                               # a few moving vehicles do not move the median
    assert frame_noise(moving, b) == frame_noise(a, b)


def test_the_gate_is_the_larger_of_min_motion_and_the_noise_times_its_factor():
    det = FrameDetections.registered(3, np.zeros((4, 2)))._replace(motion=np.array([3.0, 6.0, 9.0, 12.0]),
                                                                      noise=4.0)
    assert det.moving(min_motion=5.0).motion.tolist() == [6.0, 9.0, 12.0]
    assert det.moving(min_motion=5.0, noise_factor=2.0).motion.tolist() == [9.0, 12.0]     # max(5, 2 · 4) = 8
    assert det.moving(min_motion=5.0, noise_factor=1.0).motion.tolist() == [6.0, 9.0, 12.0]
    assert det.moving(min_motion=0.0, noise_factor=2.0).motion.tolist() == [3.0, 6.0, 9.0, 12.0]   # the gate off
