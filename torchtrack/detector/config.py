"""Detector training configuration (``configs/detector.yaml``): model, data, train and decode sections."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from torchtrack.config import from_mapping, read_mapping
from torchtrack.errors import TorchtrackError


@dataclass(frozen=True)
class ModelConfig:
    widths: tuple[int, int, int] = (32, 48, 64)
    head: int = 32
    motion: int = 16          # channels of the siamese motion encoder
    radius: int = 4           # correlation radius in stride-8 cells
    fine: int = 0             # channels of the stride-2 branch (0: none)


@dataclass(frozen=True)
class DataConfig:
    train_sequences: int = 48
    val_sequences: int = 4
    frames: int = 12                   # per cached sequence
    cache: str = "data/cache/detector"
    crop: int = 128                    # training crop (multiple of 16)
    video: dict = field(default_factory=dict)   # overrides of torchtrack.sim.video.VideoConfig
    prior_sigma: float = 1.5           # px, prior heatmap of the previous detections
    target_sigma: float = 0.8          # output cells, heatmap target
    prior_jitter: float = 1.0          # px (CenterTrack: centre jitter)
    prior_drop: float = 0.4            # probability to drop a previous peak
    prior_false: float = 0.2           # probability per object of a false peak near it
    prior_clutter: float = 6.0         # mean number of false peaks anywhere per crop
    same_frame: float = 0.05           # probability that the pair is (frame, frame) with an empty prior
    register: bool = False             # previous frame warped onto the current by the true camera motion


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 16
    steps_per_epoch: int = 130
    batch: int = 32                    # global batch (divided among torchrun ranks)
    optimizer: str = "adam"            # adam | sgd (momentum 0.9)
    lr: float = 2e-3
    weight_decay: float = 0.0
    offset_weight: float = 1.0
    velocity_weight: float = 0.5
    match_weight: float = 0.5          # cross-entropy of the matching logits on the true displacement
    out: str = "out/detector-train"
    val_frames: int = 12                # frames of each validation sequence scored per epoch


@dataclass(frozen=True)
class DecodeConfig:
    threshold: float = 0.3
    top_k: int = 1000
    radius: float = 10.0               # px, match distance for precision / recall / F1
    refine_radius: int = 6             # px, block-matching search around the network's velocity (0: off)
    refine_patch: int = 3              # half-size of the matched patch (7x7 px)
    refine_pull: float = 0.002         # pull towards the network's velocity (see detector.refine)
    continuity_reach: float = 20.0     # px, motion-continuity check with the previous velocities (0: off)


@dataclass(frozen=True)
class DetectorConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    decode: DecodeConfig = field(default_factory=DecodeConfig)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def config_from_dict(values: dict, source: str = "config") -> DetectorConfig:
    """Build a :class:`DetectorConfig` (:func:`torchtrack.config.from_mapping`); unknown sections or keys and
    values of the wrong type raise naming ``source`` and the key."""
    cfg = from_mapping(DetectorConfig, values, source)
    if cfg.train.optimizer not in ("adam", "sgd"):
        raise TorchtrackError(f"{source}: train.optimizer must be adam or sgd, got {cfg.train.optimizer!r}")
    if cfg.data.crop % 16:
        raise TorchtrackError(f"{source}: data.crop must be a multiple of 16, got {cfg.data.crop}")
    if cfg.data.video:
        from torchtrack.sim.video_config import from_dict

        from_dict(cfg.data.video, f"{source}: data.video")   # validates the keys
    return cfg


def load_config(path: str | Path | None) -> DetectorConfig:
    """Read ``configs/detector.yaml``-style YAML; ``None`` gives the defaults."""
    if path is None:
        return DetectorConfig()
    return config_from_dict(read_mapping(path, "detector config"), str(path))
