"""A distribution of cameras: ranges of the sensor and scene knobs of :class:`VideoConfig` that real wide-area and
satellite video varies, and :func:`draw_camera`, which draws one camera from them.

The ranges (``configs/detector.yaml``, ``data.cameras``) are chosen from what real sensors have: ground sampling
of 0.5-1.5 m, so that a car of 4-5 m spans 3-10 px; 1-25 frames/s, so that traffic at 5-30 m/s moves from under
a pixel to tens of pixels between frames (the range kept here, 3-18 px/frame for the median vehicle, is where a
two-frame detector can see motion at all); optics from sharp to soft (PSF σ 0.6-2 px); from clean to noisy
(σ 1-9 grey levels); dark to bright ground and from full to hazy contrast; and what the simulator lacked:
motion blur, illumination gradients, haze, coarse grey scales of 12- and 16-bit sensors squeezed to 8 bits,
and JPEG compression (:mod:`torchtrack.sim.sensor`).

A draw takes each range's value uniformly (``log``-uniformly for the positive scales: noise, vehicle length,
speed), then derives the knobs that must move together:

* vehicle lengths: ``vehicle_length = (max(2, 0.6 m), 3 m)`` around the median ``m`` (the default 5 px gives
  the default 3-15 px);
* speeds: ``speed_p90 = 1.75 s`` and ``speed_max = 3.3 s`` around the median ``s`` (12 gives 21 and 40);
* tones relative to the ground ``b`` at contrast ``c``: bright vehicles ``b + c·[40, 175]``, dark ones
  ``b - c·[50, 15]``, clipped to [0, 255] (``b = 60, c = 1`` gives the default 100-235 and 10-45);
* JPEG compression on a share ``jpeg_share`` of the cameras only;

and a share ``base_share`` of the draws keeps the base camera unchanged, so that the camera of the scenes the
pipeline's defaults were chosen on stays well represented.

The default camera lies inside every range, so the distribution contains the camera the detector was first
trained on.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from torchtrack.config import Checked, from_mapping, option
from torchtrack.sim.video_config import VideoConfig

Range = tuple[float, float]


@dataclass(frozen=True)
class CameraRanges(Checked):
    """``(low, high)`` of each knob drawn per camera (see the module docstring for the derived ones)."""

    psf_sigma: Range = option((0.6, 2.0), ge=0, ordered=True)
    noise_std: Range = option((1.0, 9.0), gt=0, ordered=True)                  # log-uniform
    gain_drift: Range = option((0.0, 0.08), ge=0, ordered=True)
    background_mean: Range = option((35.0, 170.0), ge=0, le=255, ordered=True)
    background_std: Range = option((8.0, 30.0), ge=0, ordered=True)
    forest_fraction: Range = option((0.0, 0.5), ge=0, le=1, ordered=True)
    vehicle_length_median: Range = option((3.0, 10.0), gt=0, ordered=True)     # log-uniform
    bright_fraction: Range = option((0.3, 0.8), ge=0, le=1, ordered=True)
    contrast: Range = option((0.35, 1.0), gt=0, ordered=True)                 # scales the vehicles' tone offsets
    speed_median: Range = option((3.0, 18.0), gt=0, ordered=True)              # log-uniform, px/frame
    jitter_translation: Range = option((0.3, 2.5), ge=0, ordered=True)
    parallax_px: Range = option((0.0, 1.5), ge=0, ordered=True)
    motion_blur: Range = option((0.0, 3.0), ge=0, ordered=True)
    illumination_gradient: Range = option((0.0, 0.4), ge=0, lt=1, ordered=True)
    haze: Range = option((0.0, 0.5), ge=0, lt=1, ordered=True)
    grey_step: Range = option((1.0, 4.0), ge=1, ordered=True)
    jpeg_quality: Range = option((30.0, 95.0), ge=1, le=100, ordered=True)
    jpeg_share: float = option(0.5, ge=0, le=1)                               # share of cameras that compress
    base_share: float = option(0.2, ge=0, le=1)                               # share of draws that keep the base camera

    dotted_name = "data.cameras"


LOG_UNIFORM = frozenset({"noise_std", "vehicle_length_median", "speed_median"})
DERIVED = frozenset({"contrast"})
SHARES = frozenset({"jpeg_share", "base_share"})


def ranges_from_dict(values: dict, source: str = "config") -> CameraRanges:
    """Build :class:`CameraRanges` from a ``data.cameras`` mapping (unknown keys and bad values name the key)."""
    return from_mapping(CameraRanges, values, source, "data.cameras")


def draw_camera(ranges: CameraRanges, base: VideoConfig, rng: np.random.Generator) -> VideoConfig:
    """One camera: ``base`` with every knob of ``ranges`` drawn from ``rng`` (module docstring)."""
    if rng.random() < ranges.base_share:
        return base
    drawn = {}
    for f in dataclasses.fields(ranges):
        if f.name in SHARES:
            continue
        lo, hi = getattr(ranges, f.name)
        drawn[f.name] = float(np.exp(rng.uniform(np.log(lo), np.log(hi))) if f.name in LOG_UNIFORM
                              else rng.uniform(lo, hi))
    compress = rng.random() < ranges.jpeg_share
    m, s, b, c = drawn["vehicle_length_median"], drawn["speed_median"], drawn["background_mean"], drawn["contrast"]
    knobs = {k: v for k, v in drawn.items() if k not in DERIVED}
    knobs.update(
        vehicle_length=(max(2.0, 0.6 * m), 3.0 * m),
        speed_p90=1.75 * s,
        speed_max=3.3 * s,
        bright_tone=_tones(b + c * 40.0, b + c * 175.0),
        dark_tone=_tones(b - c * 50.0, b - c * 15.0),
        jpeg_quality=int(round(drawn["jpeg_quality"])) if compress else 0,
    )
    return base.replace(**knobs)


def _tones(lo: float, hi: float) -> tuple[float, float]:
    return float(np.clip(lo, 0, 255)), float(np.clip(hi, 0, 255))
