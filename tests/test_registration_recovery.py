"""Registration of a real camera's motion: jumps, fast rotation, frames it cannot register (a new segment),
the frame-to-frame residual, and frames of another size."""

import cv2
import numpy as np
import pytest

from tests.test_registration_homography import _texture
from torchtrack.errors import TorchtrackError
from torchtrack.geometry import transfer_error
from torchtrack.pipeline.registration import Registration, RegistrationConfig

SIZE = 224


def _view(canvas: np.ndarray, camera: np.ndarray) -> np.ndarray:
    return cv2.warpPerspective(canvas, camera, (SIZE, SIZE), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)


def _rigid(angle: float, tx: float, ty: float) -> np.ndarray:
    """Frame → canvas: rotation by ``angle`` about the frame's centre, then a shift."""
    c, s = np.cos(angle), np.sin(angle)
    centre = SIZE / 2
    return np.array([[c, -s, centre - c * centre + s * centre + tx],
                     [s, c, centre - s * centre - c * centre + ty], [0, 0, 1.0]])


def _register(cameras: list[np.ndarray], canvas: np.ndarray, config: RegistrationConfig | None = None):
    """Per frame: the result and the median transfer error (px) against the true frame → frame-0 map."""
    reg = Registration(config)
    out = []
    for cam in cameras:
        result = reg(_view(canvas, cam))
        truth = np.linalg.inv(cameras[0]) @ cam
        out.append((result, float(np.median(transfer_error(result.homography, truth, (SIZE, SIZE))))))
    return out


def test_jump_is_recovered_by_the_wider_search():
    canvas = _texture((SIZE + 600, SIZE + 600), 3)
    # 4 px a frame, then a 90 px jump (beyond the flow's reach from the prediction), then 4 px a frame again.
    shifts = [4 * k for k in range(8)] + [4 * 7 + 90 + 4 * k for k in range(8)]
    cameras = [_rigid(0.0, 100 + x, 120 + 0.5 * x) for x in shifts]
    results = _register(cameras, canvas)
    assert all(r.segment == 0 for r, _ in results)
    assert results[8][0].search in ("phase", "orb")          # the jump needed the wider search
    errors = [e for _, e in results]
    assert max(errors) < 0.5
    residuals = [r.residual for r, _ in results[1:]]
    assert np.isnan(results[0][0].residual) and np.median(residuals) < 0.3


def test_fast_rotation_is_followed():
    canvas = _texture((SIZE + 600, SIZE + 600), 4)
    cameras = [_rigid(np.radians(2.5) * k, 150 + 6 * k, 150 + 3 * k) for k in range(16)]
    errors = [e for _, e in _register(cameras, canvas)]
    assert max(errors) < 0.5


def test_keyframe_mode_still_recovers_known_motion():
    canvas = _texture((SIZE + 600, SIZE + 600), 5)
    cameras = [_rigid(np.radians(0.5) * k, 150 + 5 * k, 150 - 2 * k) for k in range(12)]
    results = _register(cameras, canvas, RegistrationConfig(refresh_every=4))
    assert max(e for _, e in results) < 0.5
    assert sum(r.refreshed for r, _ in results) >= 3


def test_unregistrable_frame_starts_a_new_segment():
    first, second = _texture((SIZE + 200, SIZE + 200), 6), _texture((SIZE + 200, SIZE + 200), 7)
    reg = Registration()
    a = [reg(_view(first, _rigid(0, 50 + 3 * k, 50))) for k in range(4)]
    b = [reg(_view(second, _rigid(0, 80 + 3 * k, 60))) for k in range(4)]
    flat = reg(np.full((SIZE, SIZE), 100, np.uint8))
    assert [r.segment for r in a + b] == [0] * 4 + [1] * 4 and flat.segment == 2
    assert b[0].search == "first" and np.isnan(b[0].residual)
    # Inside the new segment the frames register to its first frame.
    truth = np.linalg.inv(_rigid(0, 80, 60)) @ _rigid(0, 89, 60)
    step = np.linalg.inv(b[0].homography) @ b[3].homography
    assert np.median(transfer_error(step, truth, (SIZE, SIZE))) < 0.3


def test_frames_of_another_size_are_named():
    reg = Registration()
    reg(_texture((64, 80), 1))
    with pytest.raises(TorchtrackError, match="frame 2 is 64x48 px, the earlier ones 80x64"):
        reg(_texture((48, 64), 1))
