"""The distribution of training cameras (torchtrack.sim.cameras) and the sensor effects (torchtrack.sim.sensor)."""

import dataclasses

import numpy as np
import pytest
import torch

from torchtrack.config import preset_path
from torchtrack.detector.config import config_from_dict, load_config
from torchtrack.errors import TorchtrackError
from torchtrack.sim.cameras import CameraRanges, draw_camera, ranges_from_dict
from torchtrack.sim.sensor import Sensor, _line_kernel
from torchtrack.sim.video import generate_sequence
from torchtrack.sim.video_config import VideoConfig

SMALL = VideoConfig(height=96, width=96, frames=2)


def test_the_default_camera_lies_inside_every_shipped_range():
    ranges = ranges_from_dict(load_config(preset_path("detector")).data.cameras)
    base = VideoConfig()
    for f in dataclasses.fields(ranges):
        if f.name in ("contrast", "jpeg_share", "base_share"):
            continue
        lo, hi = getattr(ranges, f.name)
        value = getattr(base, f.name)
        assert lo <= value <= hi or (f.name == "jpeg_quality" and value == 0), f.name
    assert ranges.contrast[0] <= 1.0 <= ranges.contrast[1]


def test_the_derived_knobs_give_the_default_camera_at_its_own_values():
    """Median 5 px, speed 12 px/frame, ground 60 and full contrast are the defaults: the derived lengths, speeds
    and tones must then be the default camera's."""
    ranges = CameraRanges(**{f.name: (v, v) for f, v in (
        (f, getattr(VideoConfig(), f.name) if hasattr(VideoConfig, f.name) else None)
        for f in dataclasses.fields(CameraRanges)) if f.name not in ("contrast", "jpeg_share", "base_share",
                                                                     "jpeg_quality")},
        contrast=(1.0, 1.0), jpeg_share=0.0, base_share=0.0)
    cam = draw_camera(ranges, VideoConfig(), np.random.default_rng(0))
    base = VideoConfig()
    for name in ("vehicle_length", "bright_tone", "dark_tone"):
        np.testing.assert_allclose(getattr(cam, name), getattr(base, name), atol=1e-9, err_msg=name)
    assert cam.speed_p90 == pytest.approx(base.speed_p90) and cam.speed_max == pytest.approx(39.6)
    assert cam.jpeg_quality == 0


def test_draws_stay_inside_the_ranges_and_repeat_for_a_seed():
    ranges = dataclasses.replace(CameraRanges(), base_share=0.0)
    for seed in range(20):
        cam = draw_camera(ranges, VideoConfig(), np.random.default_rng(seed))
        assert cam == draw_camera(ranges, VideoConfig(), np.random.default_rng(seed))
        for name in ("psf_sigma", "noise_std", "background_mean", "vehicle_length_median", "speed_median", "haze"):
            lo, hi = getattr(ranges, name)
            assert lo <= getattr(cam, name) <= hi, name
        assert cam.vehicle_length[0] <= cam.vehicle_length_median <= cam.vehicle_length[1]
        assert 0 <= cam.dark_tone[0] <= cam.dark_tone[1] <= cam.background_mean <= cam.bright_tone[0] <= 255
    shares = [draw_camera(CameraRanges(), VideoConfig(), np.random.default_rng(s)) == VideoConfig()
              for s in range(400)]
    assert 0.14 < np.mean(shares) < 0.26          # base_share 0.2


def test_an_unknown_or_bad_range_names_its_key():
    with pytest.raises(TorchtrackError, match="data.cameras.psf"):
        config_from_dict({"data": {"cameras": {"psf": [1, 2]}}}, "d.yaml")
    with pytest.raises(TorchtrackError, match="data.cameras.haze"):
        config_from_dict({"data": {"cameras": {"haze": [0.5, 0.2]}}}, "d.yaml")


def test_a_sensor_with_every_effect_off_draws_nothing_and_only_rounds():
    rng = np.random.default_rng(3)
    sensor = Sensor(SMALL, rng)
    assert rng.random() == np.random.default_rng(3).random()
    img = np.random.default_rng(1).uniform(-20, 280, (96, 96)).astype(np.float32)
    np.testing.assert_array_equal(sensor.optics(img), img)
    np.testing.assert_array_equal(sensor.digitise(img), np.clip(np.rint(img), 0, 255).astype(np.uint8))


def test_the_motion_blur_kernel_is_a_normalised_line_of_its_length():
    length, angle = 3.0, 0.7
    k = _line_kernel(length, angle).astype(np.float64)
    assert k.sum() == pytest.approx(1.0)
    r = k.shape[0] // 2
    ys, xs = np.mgrid[-r:r + 1, -r:r + 1]
    along = xs * np.cos(angle) + ys * np.sin(angle)
    across = -xs * np.sin(angle) + ys * np.cos(angle)
    assert (k * along).sum() == pytest.approx(0.0, abs=1e-6)
    # n points evenly over a segment of length L have variance L²/12 · (n+1)/(n-1); splatting each point
    # bilinearly adds f(1 - f) <= 1/4 px² along any direction
    n = int(8 * length) + 1
    assert length ** 2 / 12 <= (k * along ** 2).sum() <= length ** 2 / 12 * (n + 1) / (n - 1) + 1 / 4
    assert (k * across ** 2).sum() <= 1 / 4


def test_haze_scales_contrast_and_the_gradient_spans_its_gain():
    img = np.random.default_rng(2).normal(80, 20, (96, 96)).astype(np.float32)
    hazy = Sensor(dataclasses.replace(SMALL, haze=0.4), np.random.default_rng(0)).optics(img)
    assert hazy.std() == pytest.approx(0.6 * img.std(), rel=1e-5)
    ramp = Sensor(dataclasses.replace(SMALL, illumination_gradient=0.3), np.random.default_rng(0)).ramp
    # one side at 1 - g/2 exactly, the other within a pixel's share of the gradient of 1 + g/2
    assert min(ramp.min(), 2 - ramp.max()) == pytest.approx(0.85, abs=1e-6)
    assert abs(ramp.min() + ramp.max() - 2) <= 0.3 / 48


def test_the_grey_step_and_jpeg_change_the_frame_as_asked():
    img = np.random.default_rng(4).uniform(0, 255, (96, 96)).astype(np.float32)
    stepped = Sensor(dataclasses.replace(SMALL, grey_step=4.0), np.random.default_rng(0)).digitise(img)
    assert set(np.unique(stepped) % 4) == {0} or stepped.max() == 255
    smooth = np.tile(np.linspace(40, 200, 96, dtype=np.float32), (96, 1))
    jpeg = Sensor(dataclasses.replace(SMALL, jpeg_quality=30), np.random.default_rng(0)).digitise(smooth)
    assert 0 < np.abs(jpeg.astype(float) - np.rint(smooth)).mean() < 3


def test_default_sequences_are_unchanged_by_the_sensor_and_effects_change_them():
    plain = [f.image for f in generate_sequence(SMALL, torch.Generator().manual_seed(0))]
    again = [f.image for f in generate_sequence(SMALL.replace(haze=0.0), torch.Generator().manual_seed(0))]
    np.testing.assert_array_equal(np.stack(plain), np.stack(again))
    blurred = [f for f in generate_sequence(SMALL.replace(motion_blur=2.0), torch.Generator().manual_seed(0))]
    assert np.abs(blurred[0].image.astype(float) - plain[0]).mean() > 0.5


def test_train_init_names_a_shipped_file_or_a_path_and_refuses_weights_of_another_shape(tmp_path):
    from torchtrack.detector.config import DetectorConfig, ModelConfig, TrainConfig
    from torchtrack.detector.inference import DEFAULT_WEIGHTS
    from torchtrack.detector.train import initial_weights, train

    assert initial_weights("centertrack_small") == DEFAULT_WEIGHTS == initial_weights("centertrack_small.pt")
    assert initial_weights(str(tmp_path / "w.pt")) == tmp_path / "w.pt"
    cfg = DetectorConfig(model=ModelConfig(widths=(8, 8, 8), head=8, motion=4),
                         train=TrainConfig(init="centertrack_small", out=str(tmp_path / "out")))
    with pytest.raises(TorchtrackError, match="train.init centertrack_small: the weights do not fit"):
        train(cfg, progress=False)
