"""Registration recovers known homographies on synthetic textured frames to sub-pixel error."""

import cv2
import numpy as np
import pytest

from torchtrack.errors import TorchtrackError
from torchtrack.geometry import transfer_error
from torchtrack.pipeline.registration import Registration, RegistrationConfig


def _texture(shape: tuple[int, int], seed: int) -> np.ndarray:
    """Multi-scale smoothed noise, a ground-like texture (independent of the code under test)."""
    rng = np.random.default_rng(seed)
    img = np.zeros(shape)
    for s in (1.0, 3.0, 8.0, 20.0):
        img += cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), s) * s**0.5
    img = (img - img.mean()) / img.std()
    return np.clip(100 + 30 * img, 0, 255).astype(np.uint8)


def _camera(k: int) -> np.ndarray:
    """True map frame k → canvas: drift, slow rotation and a little perspective."""
    a = 0.008 * k
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 60 + 2.3 * k], [s, c, 50 + 1.7 * k], [1e-6 * k, -2e-6 * k, 1.0]])


def _frames(n: int, size: int = 192, seed: int = 0):
    canvas = _texture((size + 200, size + 200), seed)
    for k in range(n):
        yield k, cv2.warpPerspective(canvas, _camera(k), (size, size), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)


@pytest.mark.parametrize("method, ecc", [("lk", False), ("orb", False), ("lk", True)])
def test_recovers_known_homography(method, ecc):
    reg = Registration(RegistrationConfig(method=method, ecc=ecc, refresh_every=5))
    ref_inv = np.linalg.inv(_camera(0))
    medians = []
    for k, frame in _frames(14):
        result = reg(frame)
        truth = ref_inv @ _camera(k)  # frame k → frame 0
        medians.append(np.median(transfer_error(result.homography, truth, frame.shape)))
    assert medians[0] == 0.0
    # Several keyframe refreshes happened (refresh_every=5) and the chain still stays sub-pixel.
    assert np.median(medians) < 0.5
    assert max(medians) < 1.0


def test_transfer_error_matches_a_known_shift():
    shift = np.array([[1.0, 0, 0.3], [0, 1, -0.4], [0, 0, 1]])
    d = transfer_error(shift, np.eye(3), (32, 32))
    np.testing.assert_allclose(d, 0.5, rtol=1e-12)


def test_unknown_method_named():
    with pytest.raises(TorchtrackError, match="registration.method"):
        RegistrationConfig(method="sift")
