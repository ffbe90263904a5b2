"""Registered training pairs: the previous frame warped onto the current by the true camera motion."""

import dataclasses

import cv2
import numpy as np
import torch
from test_detector_train import tiny_config

from torchtrack.detector.dataset import PairDataset, build_cache
from torchtrack.detector.evaluate import ground_velocity, registered_motions
from torchtrack.geometry import apply_homography, warp_previous


def _homography(rng: np.random.Generator) -> np.ndarray:
    a = 0.01 * rng.normal(size=2)
    return np.array([[1 + 0.004 * rng.normal(), -a[0], 3 * rng.normal()],
                     [a[0], 1 + 0.004 * rng.normal(), 3 * rng.normal()],
                     [1e-6 * rng.normal(), 1e-6 * rng.normal(), 1.0]])


def test_warp_previous_undoes_a_known_camera_motion_and_crops_exactly():
    rng = np.random.default_rng(0)
    current = cv2.GaussianBlur(rng.uniform(0, 255, (160, 200)), (0, 0), 2.0)
    m = _homography(rng)                                  # current -> previous
    previous = cv2.warpPerspective(current, m, (200, 160), flags=cv2.INTER_CUBIC)   # previous(m x) = current(x)
    back = warp_previous(previous, m, current.shape)
    inner = (slice(20, -20), slice(20, -20))
    assert np.abs(back - current)[inner].mean() < 0.05 * current.std()   # two bilinear/cubic resamplings
    assert np.abs(previous - current)[inner].mean() > 0.2 * current.std()
    crop = warp_previous(previous, m, (64, 48), (30, 40))
    np.testing.assert_allclose(crop, back[40:104, 30:78], atol=1e-6)


def test_warp_previous_fills_what_lies_outside_the_previous_frame_from_the_current_one():
    """A pure shift by (3, -2) px: the strip whose source lies outside the previous frame takes the
    current frame's pixels (no change there); everything else is the shifted previous frame, as without
    ``fill``. A fill of the wrong shape is refused."""
    import pytest

    from torchtrack.errors import TorchtrackError

    rng = np.random.default_rng(1)
    previous = rng.uniform(0, 255, (40, 50)).astype(np.float32)
    current = rng.uniform(0, 255, (40, 50)).astype(np.float32)
    m = np.array([[1.0, 0.0, 3.0], [0.0, 1.0, -2.0], [0.0, 0.0, 1.0]])    # x_prev = x + 3, y_prev = y - 2
    plain = warp_previous(previous, m, current.shape)
    filled = warp_previous(previous, m, current.shape, fill=current)
    outside = np.zeros(current.shape, bool)
    outside[:, -3:] = True                                                  # x + 3 > 49
    outside[:2, :] = True                                                   # y - 2 < 0
    np.testing.assert_array_equal(filled[outside], current[outside])
    np.testing.assert_array_equal(filled[~outside], plain[~outside])
    np.testing.assert_array_equal(filled[2:, :-3], previous[:-2, 3:])
    with pytest.raises(TorchtrackError, match="fill has shape"):
        warp_previous(previous, m, current.shape, fill=current[:, :10])


def test_ground_velocity_is_zero_for_static_ground_and_the_reference_motion_under_a_shift():
    rng = np.random.default_rng(1)
    h_prev, h_cur = _homography(rng), _homography(rng)   # reference -> frame
    ref = rng.uniform(0, 500, (20, 2))
    xy_prev, xy_cur = apply_homography(ref, h_prev), apply_homography(ref, h_cur)
    m = registered_motions([h_prev, h_cur])[1]
    np.testing.assert_allclose(ground_velocity(xy_cur, xy_cur - xy_prev, m), 0.0, atol=1e-9)
    shift = np.array([[1.0, 0, 5.0], [0, 1.0, -2.0], [0, 0, 1.0]])   # camera translation only
    moved = ref + [3.0, 4.0]
    v = ground_velocity(apply_homography(moved, shift), apply_homography(moved, shift) - ref, np.linalg.inv(shift))
    np.testing.assert_allclose(v, np.tile([3.0, 4.0], (20, 1)), atol=1e-9)


def test_registered_pairs_cancel_the_static_ground(tmp_path):
    cfg = tiny_config(tmp_path)
    quiet = dict(prior_drop=0.0, prior_false=0.0, prior_clutter=0.0, same_frame=0.0)
    raw = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, **quiet))
    reg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, register=True, **quiet))
    cache = build_cache(cfg, "train", 0)
    a, b = PairDataset(cache, raw, 0), PairDataset(cache, reg, 0)
    rms = np.array([[(d[i][0][0] - d[i][0][1]).pow(2).mean().sqrt().item() for d in (a, b)] for i in range(16)])
    assert rms[:, 1].mean() < 0.75 * rms[:, 0].mean()


def test_stream_passes_velocities_on_from_the_second_frame_only():
    """As in the pipeline: a first frame's velocities were measured without a previous frame."""
    from types import SimpleNamespace

    from torchtrack.detector.evaluate import stream

    calls = []

    class Recorder:
        def detect(self, img, prev, prev_pts, prev_velocity=None):
            calls.append((prev is None, prev_pts is None, prev_velocity))
            return SimpleNamespace(xy=torch.ones(1, 2) * len(calls), velocity=torch.full((1, 2), float(len(calls))))

    frames = [np.zeros((8, 8), np.uint8)] * 3
    list(stream(Recorder(), frames))
    assert calls[0] == (True, True, None)
    assert calls[1][:2] == (False, False) and calls[1][2] is None
    assert calls[2][:2] == (False, False) and torch.equal(calls[2][2], torch.full((1, 2), 2.0))


def test_stream_with_given_priors_passes_them_warped_and_no_velocities():
    """``priors`` replace the previous detections (e.g. the previous truth), mapped onto the current frame."""
    from types import SimpleNamespace

    from torchtrack.detector.evaluate import stream

    calls = []

    class Recorder:
        def detect(self, img, prev, prev_pts, prev_velocity=None):
            calls.append((None if prev_pts is None else prev_pts.clone(), prev_velocity))
            return SimpleNamespace(xy=torch.full((1, 2), 50.0), velocity=torch.ones(1, 2))

    shift = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, -3.0], [0.0, 0.0, 1.0]])   # current -> previous
    truth = [np.array([[10.0, 20.0]]), np.array([[11.0, 21.0], [30.0, 40.0]]), np.zeros((0, 2))]
    frames = [np.zeros((64, 64), np.uint8)] * 3
    list(stream(Recorder(), frames, motions=[None, shift, shift], priors=[None, truth[0], truth[1]]))
    assert calls[0] == (None, None)
    for (pts, vel), given in zip(calls[1:], truth[:2]):
        assert vel is None
        np.testing.assert_allclose(pts.numpy(), given - [2.0, -3.0], atol=1e-5)


def test_unknown_prior_is_a_clear_error():
    import pytest

    from torchtrack.detector.evaluate import evaluate_frames
    from torchtrack.errors import TorchtrackError

    with pytest.raises(TorchtrackError, match="prior must be one of stream, truth, empty; got 'oracle'"):
        evaluate_frames(None, [], prior="oracle")


def test_eval_detector_prior_option_reaches_the_detector(tmp_path):
    """The shipped detector finds more vehicles with the previous truth as prior than with none, and the
    JSON says which prior was used."""
    import json

    from torchtrack.cli import main

    recall = {}
    for prior in ("truth", "empty"):
        out = tmp_path / f"{prior}.json"
        assert main(["eval-detector", "--sequences", "1", "--frames", "3", "--no-wpafb", "--prior", prior,
                     "--json", str(out)]) == 0
        result = json.loads(out.read_text())
        assert result["frames"] == 3 and result["synthetic"]["prior"] == prior
        recall[prior] = result["recall"]
    assert recall["truth"] > recall["empty"] + 0.05
