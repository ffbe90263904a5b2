"""Detector training configuration (``configs/detector.yaml``): model, data, train, decode and finetune sections."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from torchtrack.config import Checked, from_mapping, option, read_mapping
from torchtrack.detector.network import MULTIPLE
from torchtrack.geometry import area_factor


@dataclass(frozen=True)
class ModelConfig(Checked):
    widths: tuple[int, int, int] = option((32, 48, 64), ge=1)
    head: int = option(32, ge=1)
    motion: int = option(16, ge=1)                  # channels of the siamese motion encoder
    radius: int = option(4, ge=1)                   # correlation radius in stride-8 cells
    fine: int = option(0, ge=0)                     # channels of the stride-2 branch (0: none)


@dataclass(frozen=True)
class DataConfig(Checked):
    train_sequences: int = option(48, ge=1)
    val_sequences: int = option(4, ge=1)
    frames: int = option(12, ge=2)                  # per cached sequence
    cache: str = "data/cache/detector"
    crop: int = option(128, ge=16, multiple_of=16)  # training crop (multiple of 16)
    video: dict = field(default_factory=dict)       # overrides of torchtrack.sim.video.VideoConfig
    # ranges each sequence draws its camera from (torchtrack.sim.cameras.CameraRanges; {} takes its defaults;
    # None: every sequence has the camera of ``video``)
    cameras: dict | None = None
    prior_sigma: float = option(1.5, gt=0)          # px, prior heatmap of the previous detections
    target_sigma: float = option(0.8, gt=0)         # output cells, heatmap target
    prior_jitter: float = option(1.0, ge=0)         # px (CenterTrack: centre jitter)
    prior_drop: float = option(0.4, ge=0, le=1)     # probability to drop a previous peak
    prior_false: float = option(0.2, ge=0, le=1)    # probability per object of a false peak near it
    prior_clutter: float = option(6.0, ge=0)        # mean number of false peaks anywhere per crop
    same_frame: float = option(0.05, ge=0, le=1)    # probability that the pair is (frame, frame) with an empty prior
    register: bool = False                          # previous frame warped onto the current by the true camera motion


@dataclass(frozen=True)
class TrainConfig(Checked):
    epochs: int = option(16, ge=1)
    steps_per_epoch: int = option(130, ge=1)
    batch: int = option(32, ge=1)                   # global batch (divided among torchrun ranks)
    optimizer: str = option("adam", one_of=("adam", "sgd"))  # adam | sgd (momentum 0.9)
    lr: float = option(2e-3, gt=0)
    weight_decay: float = option(0.0, ge=0)
    offset_weight: float = option(1.0, ge=0)
    velocity_weight: float = option(0.5, ge=0)
    match_weight: float = option(0.5, ge=0)         # cross-entropy of the matching logits on the true displacement
    out: str = "out/detector-train"
    val_frames: int = option(12, ge=2)              # frames of each validation sequence scored per epoch
    init: str = ""                                  # weights the training starts from (a path, or the name of a
    #                                                 file shipped in torchtrack/detector/weights; "": random)


@dataclass(frozen=True)
class DecodeConfig(Checked):
    threshold: float = option(0.3, ge=0, lt=1)
    top_k: int = option(1000, ge=1)                 # most peaks in a frame of up to 512 x 512 px (see peaks_for)
    radius: float = option(10.0, gt=0)              # px, match distance for precision / recall / F1
    refine_radius: int = option(6, ge=0)            # px, block-matching search around the network's velocity (0: off)
    refine_patch: int = option(3, ge=0)             # half-size of the matched patch (7x7 px)
    refine_pull: float = option(0.002, ge=0)        # pull towards the network's velocity (see detector.refine)
    continuity_reach: float = option(20.0, ge=0)    # px, motion-continuity check with the previous velocities (0: off)
    tile: int = option(1024, ge=0)                  # px, core side of the tiles a larger frame runs in (0: whole)
    tile_batch: int = option(1, ge=1)               # tiles of one shape per network call (memory: this many tiles)

    def peaks_for(self, height: int, width: int) -> int:
        """The most peaks decoded from a ``height × width`` frame: ``top_k`` up to 512 × 512 px, scaled with
        the area above it — a constant cap would silently drop vehicles from wide-area frames (a 2048² frame
        of the synthetic scene holds about 2,500)."""
        return math.ceil(self.top_k * area_factor(height, width))

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.tile % MULTIPLE:
            raise self.refuse("tile", f"must be a multiple of {MULTIPLE} (the network's stride), got {self.tile}")


@dataclass(frozen=True)
class FinetuneConfig(Checked):
    """``train-detector --finetune``: adapting trained weights to labelled real frames (docs/detector.md)."""

    steps: int = option(300, ge=1)
    batch: int = option(16, ge=1)
    lr: float = option(2.5e-4, gt=0)                # Adam, warm-up and cosine decay over the steps
    synthetic_share: float = option(0.5, ge=0, le=1)    # probability that a training pair is synthetic
    synthetic_sequences: int = option(8, ge=1)      # cached synthetic sequences the synthetic pairs come from
    gain: float = option(0.2, ge=0, lt=1)           # real pairs: both frames scaled by U(1 - gain, 1 + gain)
    noise: float = option(0.1, ge=0)                # real pairs: Gaussian noise, in units of the frame's std
    registration: str = option("lk", one_of=("lk", "orb", "none"))   # as the pipeline's registration.method
    # vehicles the truth does not list (detections of the starting weights farther than the match radius
    # from every truth point): "dont_care" masks their neighbourhood out of the loss, "negative" keeps it
    unlabelled_static: str = option("dont_care", one_of=("dont_care", "negative"))
    unlabelled_radius: float = option(6.0, gt=0)    # px around such a detection (a vehicle's reach)
    out: str = "out/detector-finetune"


@dataclass(frozen=True)
class DetectorConfig(Checked):
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    decode: DecodeConfig = field(default_factory=DecodeConfig)
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)


def config_from_dict(values: dict, source: str = "config") -> DetectorConfig:
    """Build a :class:`DetectorConfig` (:func:`torchtrack.config.from_mapping`); unknown sections or keys and
    values of the wrong type raise naming ``source`` and the key."""
    cfg = from_mapping(DetectorConfig, values, source)
    if cfg.data.video:
        from torchtrack.sim.video_config import VideoConfig

        from_mapping(VideoConfig, cfg.data.video, source, "data.video")   # validates the keys and values
    if cfg.data.cameras is not None:
        from torchtrack.sim.cameras import ranges_from_dict

        ranges_from_dict(cfg.data.cameras, source)
    return cfg


def load_config(path: str | Path | None) -> DetectorConfig:
    """Read ``configs/detector.yaml``-style YAML; ``None`` gives the defaults."""
    if path is None:
        return DetectorConfig()
    return config_from_dict(read_mapping(path, "detector config"), str(path))
