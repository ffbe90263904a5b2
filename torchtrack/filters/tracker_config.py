"""Typed options of every multi-target tracker: type, default and meaning in one place.

One dataclass per tracker; :data:`DEFAULTS` holds each registered tracker's built-in configuration (the
labelled GM-PHD is a preset of :class:`GMPHDConfig`, the plain Panta/Clark/Vo filter). A YAML section
(``configs/gmphd.yaml``: one per tracker name) overrides the keys it gives (:func:`tracker_config`);
:func:`load_tracker_configs` reads such a file. Units: pixels and frames.

The built-in GM-PHD defaults are the best settings known on validation data (WPAFB AOI 02 truth with the
benchmark's simulated detections, seeds 100–103; ``docs/gmphd.md``, "Built-in defaults"). They follow the
input: with the detector's velocities the velocity update is on (``filter.velocity_sigma``); with positions
only, :attr:`GMPHDConfig.positions_only` is applied on top (chosen per frame, :mod:`torchtrack.filters.gmphd_input`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchtrack.config import from_mapping, preset_path, read_mapping
from torchtrack.errors import TorchtrackError


@dataclass(frozen=True)
class GMPHDFilterOptions:
    """The GM-PHD recursion (Vo & Ma 2006) with a constant-velocity model ``[x, y, vx, vy]``.

    q: CV process-noise spectral density (px²/frame³). sigma: measurement noise std (px).
    p_survival, p_detection: probabilities. clutter_density: clutter intensity per px² (30 per 585×496
    frame ≈ 1.03e-4). area: surveillance area (px²) of the log-likelihood (None: unused).
    gate_probability: χ² gate. prune_threshold: components lighter than this are dropped.
    merge_threshold: squared Mahalanobis distance ``U`` within which components merge; merge_rounds: passes.
    capacity: component cap (hits are logged and counted). extract_threshold: weight above which a component
    is an estimate. chunk: measurements per block of the update.
    velocity_sigma: the detector's velocity noise std (px/frame): with velocities given, ``[z, v]`` is the
    measurement (ours, not the paper's); None: position-only update. velocity_clutter_density: density of a
    clutter detection's velocity (1/400: uniform over ±10 px/frame). velocity_outlier: probability that a
    target's detected velocity is wrong (a mixture with the clutter's velocity density).
    """

    q: float = 2.0
    sigma: float = 1.0
    p_survival: float = 0.99
    p_detection: float = 0.9
    clutter_density: float = 1e-4
    area: float | None = None
    gate_probability: float = 0.999
    prune_threshold: float = 5e-3
    merge_threshold: float = 9.0
    merge_rounds: int = 3
    capacity: int = 1024
    extract_threshold: float = 0.5
    chunk: int = 4096
    velocity_sigma: float | None = 1.5
    velocity_clutter_density: float = 2.5e-3
    velocity_outlier: float = 0.0


@dataclass(frozen=True)
class VelocityMapOptions:
    """The velocity map of the adaptive birth (section 2.4): ``cell`` px per cell, ``shape = (rows, cols)``
    cells from ``origin = (x0, y0)``; a cell answers once it holds ``min_count`` velocities spread less than
    ``max_spread`` px/frame; ``decay`` (0, 1] forgets old velocities."""

    cell: float = 10.0
    origin: tuple[float, float] = (0.0, 0.0)
    shape: tuple[int, int] = (512, 512)
    min_count: int = 2
    max_spread: float = 2.0
    decay: float = 1.0


@dataclass(frozen=True)
class GMPHDBirthOptions:
    """Adaptive measurement-driven birth (section 2.4, eq. 4–6).

    birth_weight: weight of each birth component. sigma_pos: position std (px). sigma_vel_unknown: velocity
    std when nothing is known (births at rest); sigma_vel_detector: when initialised from the detector's
    velocity; sigma_vel_map: from the velocity map (px/frame). distance_threshold: ``T_B`` (px, eq. 4).
    suppress_weight: predicted components lighter than this do not explain measurements.
    use_detector_velocity, use_velocity_map: the two enhancements of eq. 6.
    """

    birth_weight: float = 0.05
    sigma_pos: float = 2.0
    sigma_vel_unknown: float = 8.0
    sigma_vel_detector: float = 1.5
    sigma_vel_map: float = 2.0
    distance_threshold: float = 5.0
    suppress_weight: float = 0.05
    use_detector_velocity: bool = True
    use_velocity_map: bool = True
    velocity_map: VelocityMapOptions = field(default_factory=VelocityMapOptions)


def _copy(mapping: Mapping) -> dict:
    return {k: _copy(v) if isinstance(v, Mapping) else v for k, v in mapping.items()}


POSITIONS_ONLY: dict = {"filter": {"q": 1.0, "clutter_density": 3e-4}, "birth": {"sigma_vel_unknown": 16.0},
                        "fix_separation": 12.0}
"""The enhanced GM-PHD's options on detections without velocities, over the others (validation seeds
100–103 of the WPAFB benchmark; docs/gmphd.md)."""


@dataclass(frozen=True)
class GMPHDConfig:
    """The labelled GM-PHD tracker (:class:`~torchtrack.filters.gmphd_tracker.GMPHDTracker`); the defaults are
    the enhanced GM-PHD of Aguilar, Ortner & Zerubia (2023) with this project's extensions.

    filter, birth: :class:`GMPHDFilterOptions`, :class:`GMPHDBirthOptions`.
    label_fix: the label fix of section 2.3 (off: one estimate per label, the highest weight).
    fix_separation: label-fix duplicates closer than this (px) to the label's keeper are not relabelled.
    merge_priority: with the label fix, a merged group keeps a label reported at the previous frame.
    confirm_new: a new label is reported from the second frame it is extracted (an integer n: the n-th;
    false: at once). confirm_misses: frames a new label may go unextracted without losing its count.
    settled_velocity_var: estimates with ``P_vx + P_vy`` below this feed the velocity map.
    handover_frames, handover_distance: a label lost for at most this many frames is resumed by a new
    estimate within this distance (px) of its expected path (0 frames: off).
    coast_threshold: a label reported at the previous frame stays reported while its weight exceeds this
    (through a missed detection); None: only weights above ``extract_threshold`` are reported.
    tone_sigma: spread σ_t (grey levels) of a vehicle's tone about its label's, used with the detections' grey
    levels (None: tones unused); tone_outlier: probability that a tone is unrelated; tone_rate: how fast a
    label's tone follows its detections; tone_handover_gap: the hand-over refuses tones this many σ_t apart.
    dtype: float32 (fast) or float64 (accurate).
    positions_only: options (a partial mapping of these keys) applied over the others on frames without the
    detector's velocities; ``{}``: the same options for both inputs.
    """

    filter: GMPHDFilterOptions = field(default_factory=GMPHDFilterOptions)
    birth: GMPHDBirthOptions = field(default_factory=GMPHDBirthOptions)
    label_fix: bool = True
    fix_separation: float = 8.0
    merge_priority: bool = True
    confirm_new: bool | int = True
    confirm_misses: int = 0
    settled_velocity_var: float = 4.0
    handover_frames: int = 8
    handover_distance: float = 20.0
    coast_threshold: float | None = 0.03
    tone_sigma: float | None = None
    tone_outlier: float = 0.1
    tone_rate: float = 0.1
    tone_handover_gap: float = 6.0
    dtype: str = "float32"
    positions_only: dict = field(default_factory=lambda: _copy(POSITIONS_ONLY))

    def __post_init__(self) -> None:
        if self.dtype not in ("float32", "float64"):
            raise TorchtrackError(f"dtype must be float32 or float64; got {self.dtype!r}")

    def for_input(self, velocities: bool, source: str = "config", prefix: str = "") -> GMPHDConfig:
        """The options for detections with (``velocities``) or without the detector's velocities."""
        if velocities or not self.positions_only:
            return self
        where = f"{prefix}.positions_only" if prefix else "positions_only"
        return from_mapping(GMPHDConfig, self.positions_only, source, where,
                            base=dataclasses.replace(self, positions_only={}))


LABELLED_GMPHD = GMPHDConfig(
    filter=GMPHDFilterOptions(velocity_sigma=None),
    birth=GMPHDBirthOptions(use_detector_velocity=False, use_velocity_map=False),
    label_fix=False, handover_frames=0, coast_threshold=None, confirm_new=False, positions_only={})
"""The plain labelled GM-PHD of Panta, Clark & Vo (2009) with measurement-driven birth (the paper's baseline):
no label fix and none of its extensions, births at rest, position-only update; same filter otherwise."""


@dataclass(frozen=True)
class SORTConfig:
    """SORT (Bewley et al. 2016) on centre distance: q, sigma: CV process noise and measurement std (px);
    sigma_vel: velocity std of a new track (px/frame); max_distance: assignment gate (px); max_age: frames a
    track survives unmatched; min_hits: consecutive hits before it is reported."""

    q: float = 1.0
    sigma: float = 1.0
    sigma_vel: float = 10.0
    max_distance: float = 20.0
    max_age: int = 1
    min_hits: int = 3


@dataclass(frozen=True)
class GreedyConfig:
    """CenterTrack's greedy matching: max_distance (px) between a detection moved back by its velocity and a
    previous track; max_age: frames an unmatched track is remembered (0: CenterTrack's default)."""

    max_distance: float = 10.0
    max_age: int = 0


@dataclass(frozen=True)
class PMBConfig:
    """The TOMB/P tracker (:mod:`torchtrack.filters.pmb_tracker`): q, sigma: CV process noise and measurement
    std; p_survival, p_detection; clutter_rate: false detections per frame over ``region`` ``[x0, y0, x1, y1]``
    (px), which the birth intensity also covers; birth_weight; sigma_vel: birth velocity std (px/frame);
    capacity: Bernoulli cap; estimate_threshold: existence above which a Bernoulli is reported; gate: gate
    probability; lbp_iterations: loopy belief propagation iterations."""

    q: float = 1.0
    sigma: float = 2.0
    p_survival: float = 0.99
    p_detection: float = 0.9
    clutter_rate: float = 1.0
    region: tuple[float, float, float, float] = (0.0, 0.0, 1024.0, 1024.0)
    birth_weight: float = 0.1
    sigma_vel: float = 5.0
    capacity: int = 512
    estimate_threshold: float = 0.5
    gate: float = 0.9999
    lbp_iterations: int = 30


DEFAULTS: dict[str, Any] = {"gmphd": GMPHDConfig(), "labelled-gmphd": LABELLED_GMPHD, "sort": SORTConfig(),
                            "greedy": GreedyConfig(), "pmb": PMBConfig()}
"""The built-in configuration of each registered tracker."""


def tracker_config(name: str, options: Any = None, source: str = "tracker options") -> Any:
    """Tracker ``name``'s configuration: ``options`` (its dataclass, a mapping of the keys to change, or None)
    over its built-in defaults; unknown keys and bad values are errors naming ``source`` and the key."""
    if name not in DEFAULTS:
        raise TorchtrackError(f"{source}: unknown tracker {name!r}; known: {', '.join(DEFAULTS)}")
    base = DEFAULTS[name]
    if isinstance(options, type(base)):
        config = options
    else:
        config = from_mapping(type(base), options, source, name, base=base)
    if isinstance(config, GMPHDConfig):
        config.for_input(False, source, name)      # the positions-only keys are checked here
    return config


def read_tracker_sections(path_or_preset: str | Path | None) -> dict[str, dict]:
    """The sections of a tracker-options YAML file (or shipped preset name) with one section per tracker name
    (``configs/gmphd.yaml``), as mappings of the keys they change, each checked against its tracker's
    configuration (unknown trackers, keys and bad values are errors naming the file and key); only the
    trackers with a section (None: ``{}``, every tracker runs with its defaults)."""
    if path_or_preset is None:
        return {}
    path = preset_path(path_or_preset)
    sections = read_mapping(path, "tracker config")
    unknown = sorted(set(sections) - set(DEFAULTS))
    if unknown:
        raise TorchtrackError(f"tracker config {path}: unknown tracker section(s) {unknown}; "
                              f"known: {list(DEFAULTS)}")
    for name, options in sections.items():
        tracker_config(name, options, str(path))
    return {name: dict(options or {}) for name, options in sections.items()}


def load_tracker_configs(path_or_preset: str | Path | None) -> dict[str, Any]:
    """:func:`read_tracker_sections` built into each tracker's configuration dataclass."""
    return {name: tracker_config(name, options) for name, options in read_tracker_sections(path_or_preset).items()}
