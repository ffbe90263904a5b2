"""The WPAFB real-data tracker benchmark (``torchtrack track --benchmark wpafb``).

Real vehicle truth (WPAFB 2009, AOI 02) → simulated detections (p_D, σ, clutter, velocity noise) → every
tracker (:func:`torchtrack.pipeline.detection_file.compare`) → CLEAR-MOT at the paper's 10 px, on all vehicles
and on the moving ones (:func:`torchtrack.io.moving.moving_mask`: moved more than 5 px over the last 15 frames;
the detector sees only those, as the paper's detector is trained on them, and the other vehicles are don't-care,
so ``torchtrack eval --gt OUT/moving/gt.txt --pred OUT/moving/TRACKER/tracks.txt --moving`` gives the same
scores). The settings are the ``configs/wpafb-benchmark.yaml`` preset's
(:class:`BenchmarkConfig`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchtrack.config import from_mapping
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import tracker_names
from torchtrack.io.mot import MOTData, write_motdata
from torchtrack.io.moving import moving_mask
from torchtrack.pipeline.detection_file import compare, detection_file_config
from torchtrack.sim.detections import simulate_detections

SUBSETS = ("all", "moving")


@dataclass
class SimulatedDetector:
    """The simulated detections: detection probability ``pd``, position noise ``sigma`` (px), mean false
    detections per frame ``clutter`` (uniform over ``image_size`` = W, H px), velocity noise ``velocity_sigma``
    (px/frame)."""

    pd: float = 0.9
    sigma: float = 1.0
    clutter: float = 30.0
    velocity_sigma: float | None = 1.0
    image_size: tuple[int, int] = (585, 496)


@dataclass
class MovingRule:
    """The paper's moving vehicles: moved more than ``min_displacement`` px over the last ``window`` frames."""

    min_displacement: float = 5.0
    window: int = 15


@dataclass
class BenchmarkConfig:
    """The benchmark's YAML (``configs/wpafb-benchmark.yaml``): ``truth`` (the CSV; located by the command),
    ``detections``, ``moving``, ``subsets`` (of ``all``, ``moving``), the CLEAR-MOT ``threshold`` (px), the
    ``trackers`` and ``tracker_config`` (a tracker YAML path or preset name; None: built-in defaults)."""

    truth: str = "transformed_object_states.csv"
    detections: SimulatedDetector = field(default_factory=SimulatedDetector)
    moving: MovingRule = field(default_factory=MovingRule)
    subsets: list[str] = field(default_factory=lambda: list(SUBSETS))
    threshold: float = 10.0
    trackers: list[str] = field(default_factory=tracker_names)
    tracker_config: str | None = None

    @classmethod
    def from_mapping(cls, data: dict, where: str) -> BenchmarkConfig:
        """The config of a YAML mapping (:func:`torchtrack.config.from_mapping`); unknown keys and subsets are
        refused naming ``where``."""
        config = from_mapping(cls, data, where)
        unknown = sorted(set(config.subsets) - set(SUBSETS))
        if unknown:
            raise TorchtrackError(f"{where}: unknown subset(s) {unknown} (known: {', '.join(SUBSETS)})")
        return config


@dataclass
class SubsetResult:
    """One subset: its truth, the simulated detections, tracker name → metrics and the don't-care truth lines
    (``ignore``; None: every vehicle is a target)."""

    truth: MOTData
    detections: MOTData
    results: dict[str, dict]
    ignore: np.ndarray | None = None

    @property
    def targets(self) -> MOTData:
        """The truth lines scored as objects."""
        return self.truth if self.ignore is None else self.truth.select(~self.ignore)

    def title(self, subset: str, config: BenchmarkConfig) -> str:
        """The line printed above the subset's Table 1."""
        d = config.detections
        velocity = "positions only" if d.velocity_sigma is None else f"velocity noise {d.velocity_sigma} px/frame"
        return (f"WPAFB AOI 02, {subset} vehicles ({len(set(self.targets.id.tolist()))} trajectories, "
                f"{self.targets.size} boxes, {self.detections.size} detections; p_D {d.pd}, sigma {d.sigma} px, "
                f"clutter {d.clutter:g}/frame, {velocity}; "
                f"CLEAR-MOT and HOTA at {config.threshold:g} px)")


def run_benchmark(config: BenchmarkConfig, truth: MOTData, out: str | Path, seed: int,
                  tracker_options: dict[str, dict] | None = None, trackers: list[str] | None = None
                  ) -> dict[str, SubsetResult]:
    """Every subset of ``config`` (the detections drawn with ``seed``, the same for every tracker):
    ``out/<subset>/`` gets ``gt.txt`` (the whole truth: the moving subset's non-moving vehicles are don't-care),
    ``det.txt`` and each tracker's folder. ``tracker_options``: tracker name → options; ``trackers`` overrides
    the config's."""
    stream = detection_file_config(tracker_options, config.threshold)
    d = config.detections
    found = {}
    for subset in config.subsets:
        ignore = None
        if subset == "moving":
            ignore = ~moving_mask(truth, None, config.moving.min_displacement, config.moving.window)
        seen = truth if ignore is None else truth.select(~ignore)
        det = simulate_detections(seen, pd=d.pd, sigma=d.sigma, clutter=d.clutter, image_size=d.image_size,
                                  velocity_sigma=d.velocity_sigma,
                                  generator=torch.Generator().manual_seed(seed)).detections
        sub_out = Path(out) / subset
        write_motdata(sub_out / "gt.txt", truth)
        write_motdata(sub_out / "det.txt", det)
        results = compare(det, stream, sub_out, truth, trackers or config.trackers, ignore)
        found[subset] = SubsetResult(truth, det, results, ignore)
    return found


def benchmark_payload(config: BenchmarkConfig, seed: int, found: dict[str, SubsetResult]) -> dict:
    """What ``benchmark.json`` holds: the settings and, per subset, tracker name → metrics."""
    return {"seed": seed, "detections": dataclasses.asdict(config.detections), "threshold": config.threshold,
            "subsets": {name: r.results for name, r in found.items()}}

