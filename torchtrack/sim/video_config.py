"""Configuration of the synthetic satellite-style video generator (``configs/video.yaml``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from torchtrack.config import Checked, from_mapping, option, read_mapping


@dataclass(frozen=True)
class VideoConfig(Checked):
    """Every knob of :func:`torchtrack.sim.video.generate_sequence`; defaults mimic WPAFB AOI 02.

    Lengths are in pixels, speeds in pixels per frame, rates per frame; grey levels in [0, 255];
    ``(low, high)`` pairs are ranges with ``low <= high``. The counts of roads, car parks, trees, speckles
    and buildings are those of a view of up to 512 × 512 px; a larger view scales them to keep their
    density (:func:`torchtrack.sim.video_scene.scene_counts`).
    """

    height: int = option(512, ge=32)
    width: int = option(512, ge=32)
    frames: int = option(60, ge=1)
    margin: int = option(48, ge=0)                              # world canvas beyond the view (camera jitter, entries)
    # background
    background_mean: float = option(60.0, ge=0, le=255)
    background_std: float = option(18.0, ge=0)
    forest_fraction: float = option(0.3, ge=0, le=1)
    trees: int = option(260, ge=0)                              # single dark tree crowns (false positives)
    speckles: int = option(220, ge=0)                           # static bright/dark dots (false positives)
    buildings: int = option(18, ge=0)
    building_size: tuple[float, float] = option((12.0, 45.0), gt=0, ordered=True)
    parallax_px: float = option(0.6, ge=0)                      # max roof shift per frame (false motion)
    # roads
    highways: int = option(2, ge=0)
    local_roads: int = option(3, ge=0)
    lane_width: float = option(4.0, gt=0)
    car_parks: int = option(3, ge=0)
    # vehicles
    # clip range of lengths
    vehicle_length: tuple[float, float] = option((3.0, 15.0), ge=1, ordered=True)
    vehicle_length_median: float = option(5.0, gt=0)
    bright_fraction: float = option(0.55, ge=0, le=1)
    # grey level range of bright vehicles
    bright_tone: tuple[float, float] = option((100.0, 235.0), ge=0, le=255, ordered=True)
    # grey level range of dark vehicles
    dark_tone: tuple[float, float] = option((10.0, 45.0), ge=0, le=255, ordered=True)
    lane_density: float = option(0.007, ge=0)                   # moving vehicles per px of lane at start
    birth_rate: float = option(0.025, ge=0, le=1)               # entries per lane and frame
    speed_median: float = option(12.0, gt=0)
    speed_p90: float = option(21.0, gt=0)
    speed_max: float = option(40.0, gt=0)                       # desired speeds are clipped here
    intersection_slowdown: float = option(0.7, gt=0, le=1)      # speed factor at the centre of an intersection
    intersection_radius: float = option(30.0, gt=0)
    # car following: keep a gap of 2 px + headway * speed (frames)
    headway: float = option(1.0, ge=0)
    park_gap: tuple[float, float] = option((2.0, 5.0), ge=0, ordered=True)
    park_occupancy: float = option(0.6, ge=0, le=1)
    # per slot and frame: arrival (birth) or departure (death)
    park_toggle_rate: float = option(0.004, ge=0, le=1)
    dropout_rate: float = option(0.01, ge=0, le=1)              # per vehicle and frame
    dropout_length: tuple[int, int] = option((1, 3), ge=1, ordered=True)
    # sensor and camera
    psf_sigma: float = option(1.0, ge=0)
    noise_std: float = option(2.0, ge=0)
    gain_drift: float = option(0.03, ge=0)
    jitter_translation: float = option(1.0, ge=0)
    jitter_rotation: float = option(0.002, ge=0)                # radians
    jitter_scale: float = option(0.002, ge=0)
    jitter_perspective: float = option(2e-6, ge=0)
    # sensor effects real WAMI/satellite video has (all off by default; docs/own-camera.md)
    motion_blur: float = option(0.0, ge=0)                      # px, length of a linear blur in one direction
    illumination_gradient: float = option(0.0, ge=0, lt=1)      # gain change from one side of the frame to the other
    haze: float = option(0.0, ge=0, lt=1)                       # share of contrast lost to a uniform veil
    grey_step: float = option(1.0, ge=1)                        # grey levels per step (a wide range squeezed to 8 bits)
    jpeg_quality: int = option(0, ge=0, le=100)                 # JPEG compression of each frame (0: none)
    gt_box_size: float = option(10.0, gt=0)                     # w = h of the MOTChallenge box centred on the point

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.speed_median < self.speed_p90:
            raise self.refuse("speed_p90", f"must exceed speed_median ({self.speed_median}); got {self.speed_p90}")

    def replace(self, **changes) -> VideoConfig:
        """A copy with some fields changed (unknown names are an error)."""
        return from_dict({**dataclasses.asdict(self), **changes}, "replace()")


def from_dict(values: dict, source: str = "video config", prefix: str = "") -> VideoConfig:
    """Build a :class:`VideoConfig` (:func:`torchtrack.config.from_mapping`: unknown keys, values of the wrong
    type and values out of range are errors naming ``source`` and the key, under ``prefix``)."""
    return from_mapping(VideoConfig, values, source, prefix)


def load_video_config(path: str | Path | None) -> VideoConfig:
    """Read a YAML file (the mapping may sit under a top-level ``video:`` key); ``None`` gives defaults."""
    if path is None:
        return VideoConfig()
    data = read_mapping(path, "video config")
    if set(data) == {"video"}:
        return from_dict(data["video"] or {}, str(path), "video")
    return from_dict(data, str(path))
