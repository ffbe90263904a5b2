"""Typed options of every multi-target tracker: type, default and meaning in one place.

One dataclass per tracker; :data:`DEFAULTS` holds each registered tracker's built-in configuration (the
labelled GM-PHD is a preset of :class:`GMPHDConfig`, the plain Panta/Clark/Vo filter). A YAML section
(``configs/gmphd.yaml``: one per tracker name) overrides the keys it gives (:func:`tracker_config`);
:func:`load_tracker_configs` reads such a file. Units: pixels and frames.

The built-in GM-PHD defaults are the best settings known on validation data (WPAFB AOI 02 truth with the
benchmark's simulated detections, seeds 100–103; ``docs/gmphd.md``, "Built-in defaults"). They follow the
input: with the detector's velocities the velocity update is on (``filter.velocity_sigma``); with positions
only, :attr:`GMPHDConfig.positions_only` is applied on top (chosen per frame,
:mod:`torchtrack.filters.gmphd.input_aware`).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchtrack.config import Checked, from_mapping, option, preset_path, read_mapping
from torchtrack.errors import TorchtrackError


@dataclass(frozen=True)
class GMPHDFilterOptions(Checked):
    """The GM-PHD recursion (Vo & Ma 2006) with a constant-velocity model ``[x, y, vx, vy]``.

    q: CV process-noise spectral density (px²/frame³). sigma: measurement noise std (px).
    p_survival, p_detection: probabilities. clutter_density: clutter intensity per px² (30 per 585×496
    frame ≈ 1.03e-4). area: surveillance area (px²) of the log-likelihood (None: unused).
    gate_probability: χ² gate. prune_threshold: components lighter than this are dropped.
    merge_threshold: squared Mahalanobis distance ``U`` within which components merge; merge_rounds: passes.
    capacity: the floor of the component cap, which follows the scene: ``max(capacity, 2 (measurements + live
    labels))`` per step (:meth:`~torchtrack.filters.gmphd.filter.GMPHD.capacity_for`; hits are logged and counted);
    capacity_limit: a hard limit on that cap (None: none): a scene that needs more is an error naming it, never
    a silent truncation.
    extract_threshold: weight above which a component is an estimate. chunk: unused since the update forms only
    the gated pairs (docs/scale.md); accepted so that configs naming it still load.
    velocity_sigma: the detector's velocity noise std (px/frame): with velocities given, ``[z, v]`` is the
    measurement (ours, not the paper's); None: position-only update. velocity_clutter_density: density of a
    clutter detection's velocity (1/400: uniform over ±10 px/frame). velocity_outlier: probability that a
    target's detected velocity is wrong (a mixture with the clutter's velocity density).
    """

    q: float = option(2.0, gt=0)
    sigma: float = option(1.0, gt=0)
    p_survival: float = option(0.99, gt=0, lt=1)
    p_detection: float = option(0.9, gt=0, lt=1)
    clutter_density: float = option(1e-4, gt=0)
    area: float | None = option(None, gt=0)
    gate_probability: float = option(0.999, gt=0, le=1)
    prune_threshold: float = option(5e-3, gt=0)
    merge_threshold: float = option(9.0, ge=0)
    merge_rounds: int = option(3, ge=1)
    capacity: int = option(1024, ge=1)
    capacity_limit: int | None = option(None, ge=1)
    extract_threshold: float = option(0.5, gt=0)
    chunk: int = option(4096, ge=1)
    velocity_sigma: float | None = option(1.5, gt=0)
    velocity_clutter_density: float = option(2.5e-3, gt=0)
    velocity_outlier: float = option(0.0, ge=0, lt=1)


@dataclass(frozen=True)
class VelocityMapOptions(Checked):
    """The velocity map of the adaptive birth (section 2.4): ``cell`` px per cell, ``shape = (rows, cols)``
    cells from ``origin = (x0, y0)``; a cell answers once it holds ``min_count`` velocities spread less than
    ``max_spread`` px/frame; ``decay`` (0, 1] forgets old velocities."""

    cell: float = option(10.0, gt=0)
    origin: tuple[float, float] = (0.0, 0.0)
    shape: tuple[int, int] = option((512, 512), ge=1)
    min_count: int = option(2, ge=1)
    max_spread: float = option(2.0, gt=0)
    decay: float = option(1.0, gt=0, le=1)


@dataclass(frozen=True)
class GMPHDBirthOptions(Checked):
    """Adaptive measurement-driven birth (section 2.4, eq. 4–6).

    birth_weight: weight of each birth component. sigma_pos: position std (px). sigma_vel_unknown: velocity
    std when nothing is known (births at rest); sigma_vel_detector: when initialised from the detector's
    velocity; sigma_vel_map: from the velocity map (px/frame). distance_threshold: ``T_B`` (px, eq. 4).
    suppress_weight: predicted components lighter than this do not explain measurements.
    use_detector_velocity, use_velocity_map: the two enhancements of eq. 6.
    """

    birth_weight: float = option(0.05, gt=0)
    sigma_pos: float = option(2.0, gt=0)
    sigma_vel_unknown: float = option(8.0, gt=0)
    sigma_vel_detector: float = option(1.5, gt=0)
    sigma_vel_map: float = option(2.0, gt=0)
    distance_threshold: float = option(5.0, ge=0)
    suppress_weight: float = option(0.05, ge=0)
    use_detector_velocity: bool = True
    use_velocity_map: bool = True
    velocity_map: VelocityMapOptions = field(default_factory=VelocityMapOptions)


POSITIONS_ONLY: dict = {"filter": {"q": 1.0, "clutter_density": 3e-4}, "birth": {"sigma_vel_unknown": 16.0},
                        "fix_separation": 12.0}
"""The enhanced GM-PHD's options on detections without velocities, over the others (validation seeds
100–103 of the WPAFB benchmark; docs/gmphd.md)."""


@dataclass(frozen=True)
class GMPHDConfig(Checked):
    """The labelled GM-PHD tracker (:class:`~torchtrack.filters.gmphd.tracker.GMPHDTracker`); the defaults are
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
    fix_separation: float = option(8.0, ge=0)
    merge_priority: bool = True
    confirm_new: bool | int = option(True, ge=1)
    confirm_misses: int = option(0, ge=0)
    settled_velocity_var: float = option(4.0, ge=0)
    handover_frames: int = option(8, ge=0)
    handover_distance: float = option(20.0, ge=0)
    coast_threshold: float | None = option(0.03, gt=0)
    tone_sigma: float | None = option(None, gt=0)
    tone_outlier: float = option(0.1, gt=0, lt=1)
    tone_rate: float = option(0.1, gt=0, le=1)
    tone_handover_gap: float = option(6.0, gt=0)
    dtype: str = option("float32", one_of=("float32", "float64"))
    positions_only: dict = field(default_factory=lambda: copy.deepcopy(POSITIONS_ONLY))

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
class SORTConfig(Checked):
    """SORT (Bewley et al. 2016) on centre distance: q, sigma: CV process noise and measurement std (px);
    sigma_vel: velocity std of a new track (px/frame); max_distance: assignment gate (px); max_age: frames a
    track survives unmatched; min_hits: consecutive hits before it is reported."""

    q: float = option(1.0, ge=0)
    sigma: float = option(1.0, gt=0)
    sigma_vel: float = option(10.0, gt=0)
    max_distance: float = option(20.0, gt=0)
    max_age: int = option(1, ge=0)
    min_hits: int = option(3, ge=0)


@dataclass(frozen=True)
class GreedyConfig(Checked):
    """CenterTrack's greedy matching: max_distance (px) between a detection moved back by its velocity and a
    previous track; max_age: frames an unmatched track is remembered (0: CenterTrack's default)."""

    max_distance: float = option(10.0, gt=0)
    max_age: int = option(0, ge=0)


@dataclass(frozen=True)
class PMBConfig(Checked):
    """The TOMB/P tracker (:mod:`torchtrack.filters.pmb.tracker`): q, sigma: CV process noise and measurement
    std; p_survival, p_detection; clutter_rate: false detections per frame over ``region`` ``[x0, y0, x1, y1]``
    (px), which the birth intensity also covers; birth_weight: the least expected births per frame; birth_density:
    expected births per frame per megapixel of ``region`` (the birth intensity's weight is
    ``max(birth_weight, birth_density · area)``, so that births follow the region as clutter does; the default
    leaves a 1024² region at ``birth_weight``); sigma_vel: birth velocity std (px/frame);
    capacity: the floor of the Bernoulli slots, which follow the scene (every Bernoulli above the pruning
    threshold is kept: ``max(capacity, kept)`` slots); capacity_limit: a hard limit on the Bernoullis kept (None: none),
    more is an error naming it; estimate_threshold: existence above which a Bernoulli is reported; gate: gate
    probability; lbp_iterations: loopy belief propagation iterations (on the gated pairs only)."""

    q: float = option(1.0, gt=0)
    sigma: float = option(2.0, gt=0)
    p_survival: float = option(0.99, ge=0, le=1)
    p_detection: float = option(0.9, ge=0, le=1)
    clutter_rate: float = option(1.0, ge=0)
    region: tuple[float, float, float, float] = (0.0, 0.0, 1024.0, 1024.0)
    birth_weight: float = option(0.1, ge=0)
    birth_density: float = option(0.09, ge=0)
    sigma_vel: float = option(5.0, gt=0)
    capacity: int = option(512, ge=1)
    capacity_limit: int | None = option(None, ge=1)
    estimate_threshold: float = option(0.5, gt=0, lt=1)
    gate: float = option(0.9999, gt=0, le=1)
    lbp_iterations: int = option(30, ge=1)

    def __post_init__(self) -> None:
        super().__post_init__()
        x0, y0, x1, y1 = self.region
        if not (x0 < x1 and y0 < y1):
            raise self.refuse("region", f"must be [x0, y0, x1, y1] with x0 < x1 and y0 < y1; got {list(self.region)}")


@dataclass(frozen=True)
class GLMBConfig(Checked):
    """The joint δ-GLMB tracker (:mod:`torchtrack.filters.glmb.tracker`; docs/glmb.md). q, sigma: CV process noise
    (px²/frame³) and position noise std (px); velocity_sigma: the detector's velocity noise std (px/frame): with
    velocities given, ``[z, v]`` is the measurement (None: positions only); p_survival, p_detection;
    clutter_density: false detections per px²; velocity_clutter_density: density of a false detection's velocity;
    gate: χ² gate probability; chains: Gibbs chains per hypothesis group and frame, shared among its hypotheses in
    proportion to √w_h; sweeps: samples per chain; prune_threshold: lighter hypotheses are dropped;
    max_hypotheses: the cap per group (hits counted, warned once);
    birth_rate: the least expected births per frame λ_0; birth_density: expected births per frame per megapixel of
    the frame's detections' bounding box ρ_B (λ_B = max(λ_0, ρ_B A), docs/glmb.md (B2));
    birth_max, birth_min: cap and floor of a birth's existence;
    birth_sigma_pos (px), birth_sigma_vel (px/frame, births at rest), birth_sigma_vel_detector (from the
    detector's velocity); birth_pairs: positions only, each measurement's births pair it with at most this many
    measurements of the previous frame within birth_max_speed (px/frame), velocity std birth_sigma_vel_pair
    (px/frame) (docs/glmb.md (B3)); 0: births at rest (B1); confirm_frames: a label is reported from its n-th
    consecutive frame in the estimate;
    seed: the sampler's random stream; dtype."""

    q: float = option(1.0, gt=0)
    sigma: float = option(1.0, gt=0)
    velocity_sigma: float | None = option(1.5, gt=0)
    p_survival: float = option(0.97, gt=0, lt=1)
    p_detection: float = option(0.9, gt=0, le=1)
    clutter_density: float = option(2e-4, gt=0)
    velocity_clutter_density: float = option(2.5e-3, gt=0)
    gate: float = option(0.999, gt=0, lt=1)
    chains: int = option(32, ge=1)
    sweeps: int = option(2, ge=1)
    prune_threshold: float = option(1e-4, gt=0, lt=1)
    max_hypotheses: int = option(30, ge=1)
    birth_rate: float = option(0.3, gt=0)
    birth_density: float = option(1.0, ge=0)
    birth_max: float = option(0.5, gt=0, lt=1)
    birth_min: float = option(1e-3, gt=0, lt=1)
    birth_sigma_pos: float = option(2.0, gt=0)
    birth_sigma_vel: float = option(8.0, gt=0)
    birth_sigma_vel_detector: float = option(1.5, gt=0)
    birth_pairs: int = option(3, ge=0)
    birth_max_speed: float = option(25.0, gt=0)
    birth_sigma_vel_pair: float = option(2.0, gt=0)
    confirm_frames: int = option(3, ge=1)
    seed: int = option(0, ge=0)
    dtype: str = option("float64", one_of=("float32", "float64"))


DEFAULTS: dict[str, Any] = {"gmphd": GMPHDConfig(), "labelled-gmphd": LABELLED_GMPHD, "sort": SORTConfig(),
                            "greedy": GreedyConfig(), "pmb": PMBConfig(),
                            "glmb": GLMBConfig()}
"""The built-in configuration of each registered tracker."""


def tracker_config(name: str, options: Any = None, source: str = "tracker options") -> Any:
    """Tracker ``name``'s configuration: ``options`` (its dataclass, a mapping of the keys to change, or None)
    over its built-in defaults; unknown keys and bad values are errors naming ``source`` and the key."""
    if name not in DEFAULTS:
        raise TorchtrackError(f"{source}: unknown tracker {name!r}; known: {', '.join(DEFAULTS)}")
    base = DEFAULTS[name]
    config = from_mapping(type(base), options, source, name, base=base)     # a dataclass is taken as it is
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
