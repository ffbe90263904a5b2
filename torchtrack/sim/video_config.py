"""Configuration of the synthetic satellite-style video generator (``configs/video.yaml``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from torchtrack.config import from_mapping, read_mapping
from torchtrack.errors import TorchtrackError


@dataclass(frozen=True)
class VideoConfig:
    """Every knob of :func:`torchtrack.sim.video.generate_sequence`; defaults mimic WPAFB AOI 02.

    Lengths are in pixels, speeds in pixels per frame, rates per frame.
    """

    height: int = 512
    width: int = 512
    frames: int = 60
    margin: int = 48                       # world canvas beyond the view (camera jitter, entries)
    # background
    background_mean: float = 60.0
    background_std: float = 18.0
    forest_fraction: float = 0.3
    trees: int = 260                       # single dark tree crowns (false positives)
    speckles: int = 220                    # static bright/dark dots (false positives)
    buildings: int = 18
    building_size: tuple[float, float] = (12.0, 45.0)
    parallax_px: float = 0.6               # max roof shift per frame (false motion)
    # roads
    highways: int = 2
    local_roads: int = 3
    lane_width: float = 4.0
    car_parks: int = 3
    # vehicles
    vehicle_length: tuple[float, float] = (3.0, 15.0)   # clip range of lengths
    vehicle_length_median: float = 5.0
    bright_fraction: float = 0.55
    bright_tone: tuple[float, float] = (100.0, 235.0)   # grey level range of bright vehicles
    dark_tone: tuple[float, float] = (10.0, 45.0)       # grey level range of dark vehicles
    lane_density: float = 0.007           # moving vehicles per px of lane at start
    birth_rate: float = 0.025              # entries per lane and frame
    speed_median: float = 12.0
    speed_p90: float = 21.0
    speed_max: float = 40.0              # desired speeds are clipped here
    intersection_slowdown: float = 0.7    # speed factor at the centre of an intersection
    intersection_radius: float = 30.0
    headway: float = 1.0                  # car following: keep a gap of 2 px + headway * speed (frames)
    park_gap: tuple[float, float] = (2.0, 5.0)
    park_occupancy: float = 0.6
    park_toggle_rate: float = 0.004        # per slot and frame: arrival (birth) or departure (death)
    dropout_rate: float = 0.01             # per vehicle and frame
    dropout_length: tuple[int, int] = (1, 3)
    # sensor and camera
    psf_sigma: float = 1.0
    noise_std: float = 2.0
    gain_drift: float = 0.03
    jitter_translation: float = 1.0
    jitter_rotation: float = 0.002         # radians
    jitter_scale: float = 0.002
    jitter_perspective: float = 2e-6
    gt_box_size: float = 10.0              # w = h of the MOTChallenge box centred on the point

    def __post_init__(self) -> None:
        if self.height < 32 or self.width < 32:
            raise TorchtrackError(f"video config: frame size {self.height}x{self.width} is below 32x32")
        if self.frames < 1:
            raise TorchtrackError(f"video config: frames must be >= 1, got {self.frames}")
        lo, hi = self.vehicle_length
        if not 1.0 <= lo <= hi:
            raise TorchtrackError(f"video config: vehicle_length must satisfy 1 <= min <= max, got {lo}, {hi}")
        if not 0 < self.speed_median < self.speed_p90:
            raise TorchtrackError("video config: need 0 < speed_median < speed_p90")

    def replace(self, **changes) -> VideoConfig:
        """A copy with some fields changed (unknown names are an error)."""
        return from_dict({**dataclasses.asdict(self), **changes}, "replace()")


def from_dict(values: dict, source: str = "config") -> VideoConfig:
    """Build a :class:`VideoConfig` (:func:`torchtrack.config.from_mapping`: unknown keys and values of the
    wrong type are errors naming ``source`` and the key)."""
    return from_mapping(VideoConfig, values, f"{source} (video config)")


def load_video_config(path: str | Path | None) -> VideoConfig:
    """Read a YAML file (the mapping may sit under a top-level ``video:`` key); ``None`` gives defaults."""
    if path is None:
        return VideoConfig()
    data = read_mapping(path, "video config")
    if set(data) == {"video"}:
        data = data["video"] or {}
    return from_dict(data, str(path))
