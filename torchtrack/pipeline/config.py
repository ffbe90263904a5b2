"""Settings of the video pipeline (``configs/pipeline.yaml``); the defaults are the embedded ones."""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchtrack.config import Checked, from_mapping, option, read_mapping
from torchtrack.detector.network import MULTIPLE
from torchtrack.filters.trackers.options import DEFAULTS, tracker_config
from torchtrack.pipeline.registration import RegistrationConfig
from torchtrack.sim.video_config import VideoConfig
from torchtrack.threads import TRACKER_THREADS

SELECTED_TRACKERS: dict = {
    "gmphd": {"fix_separation": 4.0, "confirm_new": True, "handover_distance": 10.0, "coast_threshold": 0.03,
              "tone_sigma": 4.0,
              "filter": {"velocity_sigma": 1.0, "velocity_outlier": 0.3, "p_detection": 0.8, "q": 1.0,
                         "clutter_density": 1e-5},
              "birth": {"birth_weight": 0.05}, "positions_only": {}},
    "labelled-gmphd": {"filter": {"p_detection": 0.9, "q": 1.0, "clutter_density": 3e-4}},
    "sort": {"max_distance": 30.0, "max_age": 1, "min_hits": 3},
    "greedy": {"max_distance": 20.0, "max_age": 2},
}
"""Per-tracker options of the embedded defaults (the keys that differ from each tracker's built-in defaults,
:mod:`torchtrack.filters.trackers.options`), with ``min_speed 2`` and ``min_motion 5``: chosen by
``torchtrack select-trackers --sequences out/val --min-speeds 1 2 --min-motions 5 8`` on the detector's
validation-split sequences, with the fixed-lag output and weak detections of the defaults; the GM-PHD's
``tone_sigma`` (a grey level per label) added after a comparison on 32 validation sequences (docs/pipeline.md).
The GM-PHD keeps these options on the first frame too, which has no velocities (``positions_only: {}``)."""


TRAINED_VEHICLE_LENGTH = VideoConfig().vehicle_length_median
"""px: the median vehicle length of the detector's training video."""


@dataclass
class PipelineConfig(Checked):
    """Every knob of the tracker stream and of :func:`torchtrack.pipeline.track_video.track_video`.

    tracker / tracker_options: the tracker's name and its options (``make_tracker(name, options)``).
    trackers: options per tracker name for the trackers compared on the same detections (``demo``,
    ``track --compare``); ``tracker_options``, where given, overrides the entry of ``tracker``.
    min_speed, min_motion: the paper tracks moving objects only: detections whose predicted speed (the
    detector's velocity head, px/frame) or whose motion evidence (mean absolute difference to the registered
    previous frame around the detection, grey levels; ``detection.motion_evidence``) is below these are
    not given to the tracker (they are still recorded in ``detections.txt`` and feed the detector's prior
    heatmap). 0 passes every detection.
    motion_noise_factor: the motion-evidence threshold is at least this times the frame difference's noise
    level (``detection.frame_noise``: the median absolute difference to the registered previous frame), so that
    on a noisy camera the sensor's noise does not pass for motion (0: ``min_motion`` alone; with ``min_motion``
    0 the motion gate is off, this part too). 1.5, the best mean MOTA of 0, 1.5, 1.75 and 2 on twelve validation
    cameras (docs/benchmarks.md#cameras), leaves the default camera's gate at ``min_motion`` and raises it on the
    noisy ones.
    gate_registration: the motion-evidence threshold is raised by this times the difference the
    registration's frame-to-frame residual leaves at the detection (residual × local gradient,
    ``detection.misregistration``): on a real camera edges of roofs and roads then stop passing for motion
    where the registration is off by a fraction of a pixel (0: off). Only the part beyond one grey level
    counts (``frame_detections.gate_margin``), and only on frames where the plain gate (``min_motion``) passes
    more than ``gate_budget`` of the pixels: on a frame where it passes fewer, they are the vehicles' and the
    gate stays as it is.
    detector_weights: a weights file (``None``: the shipped weights).
    vehicle_length: the vehicles' typical length in this video (px): the detector gets the frames resampled by
    :data:`TRAINED_VEHICLE_LENGTH` / ``vehicle_length`` (the scale it was trained at) and its detections are
    mapped back into the frame (``None``: frames as they are).
    detector_tile: a frame larger than this (px, a multiple of 16) is detected in tiles of this side, each
    with 128 px of frame around it, with the whole frame's result and memory bounded by the tiles
    (``torchtrack.detector.inference``; ``None``: the detector's own setting, 1024; 0: whole frames).
    detector_backend: ``float`` (default) or ``int8``: the network in int8 on the CPU with the weights' int8
    calibration (``torchtrack.detector.quantized``; about twice as fast on one core, the same F1; tiles and
    strips then equal the whole frame's detections only up to quantisation steps); ``auto``: int8 where
    calibrated.
    detection_threshold: decode the detector's heatmap down to this score (``None``: the detector's own
    calibrated threshold); lower values raise recall when the moving-object gate removes the false alarms.
    weak_threshold, weak_distance: detections decoded between ``weak_threshold`` and the detection
    threshold are given to the tracker only where they continue a track: their position minus their
    velocity within ``weak_distance`` px of a track reported at the previous frame (``None``: off;
    :mod:`torchtrack.pipeline.tracker_stream`).
    weak_continues_pending: weak detections may also continue a new track the tracker extracted at the
    previous frame but has not reported yet (a GM-PHD label waiting for ``confirm_new``).
    output_lag, lag_distance: a frame's tracks are written ``output_lag`` frames later, after backfilling
    new tracks, filling short gaps and trimming coasting tails with what those frames showed (0: online;
    :mod:`torchtrack.pipeline.fixed_lag`).
    merge_distance, merge_age: on frames within ``merge_age`` frames of one where the moving-object gate was
    raised (``gate_budget``), a track younger than ``merge_age`` frames within ``merge_distance`` px of an older
    one is left out (a second response to one vehicle or to the clutter beside it; 0: off; needs
    ``output_lag`` > 0; :mod:`torchtrack.pipeline.fixed_lag`).
    prior: where the detector's prior heatmap comes from: the previous frame's ``detections`` (the
    paper's eq. 1) or its ``tracks``.
    threshold: CLEAR-MOT centre-distance threshold in pixels (the paper's 10 px).
    video, video_fps, trail, box, scale, draw_truth: the annotated video (``box=None`` draws dots).
    snapshots: frame numbers saved as PNG beside the video.
    dtype: the tracker's floating-point type.
    device: where the trackers run (``cpu``, ``cuda``, ``cuda:N``): each frame's detections are put there and the
    trackers follow them (:mod:`torchtrack.filters.trackers.protocol`).
    threads: torch intra-op threads of the detector and the registration (default 1: the other core serves the
    concurrent frame decoding, registration and video encoding; on a loaded 2-core machine two torch
    threads made the detector 10–20 times slower, spinning against each other).
    tracker_threads: torch intra-op threads of each tracker step (default
    :data:`torchtrack.threads.TRACKER_THREADS`, one: the trackers' tensors are small, see
    :mod:`torchtrack.threads`), whatever ``threads`` is.
    """

    tracker: str = option("gmphd", one_of=tuple(DEFAULTS))
    tracker_options: dict = field(default_factory=dict)
    trackers: dict = field(default_factory=lambda: copy.deepcopy(SELECTED_TRACKERS))
    min_speed: float = option(2.0, ge=0)
    min_motion: float = option(5.0, ge=0)
    motion_noise_factor: float = option(1.5, ge=0)
    gate_registration: float = option(3.0, ge=0)
    gate_budget: float = option(0.05, ge=0, le=1)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    detector_weights: str | None = None
    vehicle_length: float | None = option(None, gt=0)
    detector_tile: int | None = option(None, ge=0)
    detector_backend: str = option("float", one_of=("auto", "float", "int8"))
    detection_threshold: float | None = option(None, ge=0, lt=1)
    weak_threshold: float | None = option(0.15, gt=0, lt=1)
    weak_distance: float = option(2.5, gt=0)
    weak_continues_pending: bool = False
    output_lag: int = option(3, ge=0)
    lag_distance: float = option(3.0, gt=0)
    merge_distance: float = option(6.0, ge=0)
    merge_age: int = option(10, ge=1)
    prior: str = option("detections", one_of=("detections", "tracks"))
    threshold: float = option(10.0, gt=0)
    video: bool = True
    video_fps: float = option(10.0, gt=0)
    trail: int = option(12, ge=0)
    box: int | None = option(None, ge=1)
    scale: int = option(1, ge=1)
    draw_truth: bool = True
    snapshots: tuple[int, ...] = option((1,), ge=1)
    dtype: str = option("float64", one_of=("float32", "float64"))
    device: str = "cpu"
    threads: int = option(1, ge=1)
    tracker_threads: int = option(TRACKER_THREADS, ge=1)

    def __post_init__(self) -> None:
        if isinstance(self.registration, dict):
            self.registration = from_mapping(RegistrationConfig, self.registration, "pipeline config", "registration")
        self.snapshots = tuple(self.snapshots)
        super().__post_init__()
        if isinstance(self.output_lag, bool) or not isinstance(self.output_lag, int):
            raise self.refuse("output_lag", f"must be a whole number of frames; got {self.output_lag!r}")
        if self.detector_tile is not None and self.detector_tile % MULTIPLE:
            raise self.refuse("detector_tile", f"must be a multiple of {MULTIPLE} (the network's stride); "
                                               f"got {self.detector_tile}")
        try:
            device = torch.device(self.device)
        except (RuntimeError, TypeError):
            raise self.refuse("device", f"must be cpu, cuda or cuda:N; got {self.device!r}") from None
        if device.type == "cuda" and not torch.cuda.is_available():
            raise self.refuse("device", f"is {self.device}, but torch sees no CUDA device here")
        if not isinstance(self.trackers, dict) or not all(isinstance(v, dict) for v in self.trackers.values()):
            raise self.refuse("trackers", "must map tracker names to option mappings")

    @property
    def detector_scale(self) -> float:
        """The factor the detector's frames are resampled by (``vehicle_length``)."""
        return 1.0 if self.vehicle_length is None else TRAINED_VEHICLE_LENGTH / self.vehicle_length

    def options_for(self, name: str) -> dict | None:
        """The options tracker ``name`` runs with in the pipeline (``None``: its defaults)."""
        if name == self.tracker and self.tracker_options:
            return self.tracker_options
        return self.trackers.get(name) or None

    def replace(self, **changes) -> PipelineConfig:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


def load_pipeline_config(path: str | Path | None) -> PipelineConfig:
    """Read a pipeline YAML (the mapping may sit under a top-level ``pipeline:`` key); ``None``: defaults.
    Each ``trackers`` entry holds the keys to change from that tracker's built-in defaults
    (:mod:`torchtrack.filters.trackers.options`), checked here."""
    if path is None:
        return PipelineConfig()
    where = f"pipeline config {path}"
    data = read_mapping(path, "pipeline config")
    if set(data) == {"pipeline"}:
        data = data["pipeline"] or {}
    config = from_mapping(PipelineConfig, data, where)
    for name, options in config.trackers.items():
        tracker_config(name, options, where + ": trackers")
    if config.tracker_options:
        tracker_config(config.tracker, config.tracker_options, where + ": tracker_options")
    return config
