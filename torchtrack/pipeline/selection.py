"""Choose the video pipeline's tracker settings on validation sequences (``torchtrack select-trackers``).

The detector runs once per sequence (:func:`collect`); then, for every moving-object gate
``(min_speed, min_motion)`` of the grid and every tracker, each option set of that tracker's grid runs on the
same kept detections and is scored by pooled CLEAR-MOT over all sequences (:func:`evaluate`). Per gate each
tracker keeps its best option set (:func:`choose`: the best IDF1 among the sets level in MOTA); the gate is
the one where the pipeline's own tracker scores best, so that every tracker is compared on the same
detections (:func:`select`). The result is a pipeline config
(``min_speed``, ``min_motion`` and ``trackers``) for ``torchtrack demo --config`` /
``torchtrack track --pipeline-config``.

Selection must use sequences that are not the ones reported: the demo and the held-out sequences are drawn
from the detector's test split, so validate on other seeds (docs/pipeline.md).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.io.mot import MOTData, read_mot
from torchtrack.io.moving import dont_care
from torchtrack.metrics.table import score
from torchtrack.pipeline.config import PipelineConfig
from torchtrack.pipeline.frame_detections import FrameDetections
from torchtrack.pipeline.replay import run_tracker
from torchtrack.pipeline.sequences import concatenate, find_sequences
from torchtrack.pipeline.track_video import track_video

GRIDS: dict[str, dict[str, list]] = {
    "gmphd": {"fix_separation": [4.0, 5.0], "confirm_new": [True, False, 3], "confirm_misses": [3],
              "filter.velocity_sigma": [1.0], "filter.velocity_outlier": [0.3], "filter.p_detection": [0.8, 0.9],
              "filter.q": [0.5, 1.0, 2.0],
              "filter.clutter_density": [1e-4, 1e-5], "birth.birth_weight": [0.05],
              "handover_distance": [10.0], "coast_threshold": [0.03, 0.1], "tone_sigma": [None, 4.0],
              "positions_only": [{}]},
    "labelled-gmphd": {"filter.p_detection": [0.8, 0.9], "filter.q": [1.0, 2.0],
                       "filter.clutter_density": [1e-4, 3e-4]},
    "sort": {"max_distance": [10.0, 20.0, 30.0], "max_age": [1, 3], "min_hits": [1, 3]},
    "greedy": {"max_distance": [10.0, 20.0], "max_age": [0, 2]},
    "pmb": {},
}
"""Option grids per tracker; a dotted key ``section.key`` sets ``options[section][key]``. The GM-PHD's
``positions_only: {}`` keeps the chosen options on the pipeline's first frame, which has no detector velocities
(as ``SELECTED_TRACKERS`` does)."""


@dataclass
class SequenceDetections:
    """One validation sequence: its truth, don't-care mask and the detector's kept detections."""

    name: str
    gt: MOTData
    ignore: np.ndarray | None
    detections: list[FrameDetections]


def collect(root: str | Path, out: str | Path, config: PipelineConfig, detector=None,
            progress: bool = True) -> list[SequenceDetections]:
    """Run registration and detection once on every sequence of ``root`` that has truth, scored on its moving
    vehicles (:func:`torchtrack.io.moving.dont_care`, as ``track --sequences`` by default)."""
    data = []
    cfg = config.replace(video=False)
    for seq in find_sequences(root):
        if seq.gt is None:
            continue
        gt = read_mot(seq.gt)
        ignore = dont_care(gt, "moving", seq.velocity)
        result = track_video(seq.source(), Path(out) / seq.name, cfg, detector=detector, gt=gt,
                             gt_path=str(seq.gt), ignore=ignore, keep_detections=True, progress=progress)
        data.append(SequenceDetections(seq.name, gt, ignore, result.detections))
    return data


def option_sets(grid: dict[str, list]) -> list[dict]:
    """Every combination of ``grid`` as a nested options mapping (``{}`` for an empty grid)."""
    sets = []
    for values in itertools.product(*grid.values()):
        options: dict = {}
        for key, value in zip(grid, values):
            section, _, name = key.rpartition(".")
            (options.setdefault(section, {}) if section else options)[name] = value
        sets.append(options)
    return sets


def evaluate(name: str, options: dict | None, gate: tuple[float, float], data: list[SequenceDetections],
             config: PipelineConfig) -> dict:
    """Pooled CLEAR-MOT and HOTA (:func:`~torchtrack.metrics.table.score`) of tracker ``name`` with ``options``
    on the detections that pass ``gate = (min_speed, min_motion)`` (:meth:`FrameDetections.moving`), over ``data``."""
    run = config.replace(tracker=name, tracker_options={}, trackers={name: options or {}}, min_speed=gate[0],
                         min_motion=gate[1])
    parts, masks = [], []
    for seq in data:
        parts.append((seq.gt, run_tracker(make_tracker(name, run.options_for(name)), run, seq.detections).tracks))
        masks.append(seq.ignore if seq.ignore is not None else np.zeros(seq.gt.size, bool))
    return score(*concatenate(parts), config.threshold, np.concatenate(masks))


def choose(rows: list[dict], mota_tolerance: float = 0.0, max_ids: float | None = None) -> dict:
    """The row (``MOTA``, ``IDF1``, ...) with the highest IDF1 among those within ``mota_tolerance`` of the
    highest MOTA (the first such row on ties). With ``max_ids``, only the rows with at most that many
    identity switches compete (all rows when none has so few)."""
    rows = [r for r in rows if max_ids is None or r["IDS"] <= max_ids] or rows
    top = max(r["MOTA"] for r in rows)
    return max((r for r in rows if r["MOTA"] >= top - mota_tolerance), key=lambda r: r["IDF1"])


def pipeline_tracker(config: PipelineConfig, trackers: list[str]) -> str:
    """The tracker whose score picks the gate: the pipeline's own if it is among ``trackers``, else the first."""
    return config.tracker if config.tracker in trackers else trackers[0]


def check_ids_reference(reference: str, config: PipelineConfig, trackers: list[str]) -> None:
    """Raise unless ``reference`` is one of ``trackers`` other than the pipeline's own (the tracker whose
    identity switches :func:`select`'s ``ids_limit`` refers to)."""
    main = pipeline_tracker(config, trackers)
    if reference not in trackers or reference == main:
        raise TorchtrackError(f"the identity-switch reference {reference!r} must be one of the trackers selected "
                              f"({', '.join(trackers)}) other than the pipeline's own ({main!r})")


def select(data: list[SequenceDetections], config: PipelineConfig, trackers: list[str],
           gates: list[tuple[float, float]], grids: dict[str, dict[str, list]] | None = None,
           progress: bool = True, mota_tolerance: float = 0.0,
           ids_limit: tuple[str, float] | None = None) -> tuple[PipelineConfig, list[dict]]:
    """Grid search (module docstring) over the ``(min_speed, min_motion)`` ``gates``; returns the chosen
    config and every evaluation (``tracker, min_speed, min_motion, options, MOTA, HOTA, IDS, FP, FN, IDF1``).

    Per gate and tracker the option set with the highest IDF1 among those within ``mota_tolerance`` of the
    best MOTA is kept (0: the best MOTA): MOTA differences of a few thousandths are noise on a few
    validation sequences, and among such options IDF1 prefers the one that keeps identities. With
    ``ids_limit = (reference, ratio)`` the pipeline's tracker chooses only among the option sets with at most
    ``ratio`` times the identity switches of ``reference``'s chosen options at the same gate."""
    grids = GRIDS if grids is None else grids
    if ids_limit is not None:
        check_ids_reference(ids_limit[0], config, trackers)
    runs = [(g, name, o) for g in gates for name in trackers for o in option_sets(grids.get(name, {}))]
    log = []
    rows: dict[tuple[tuple[float, float], str], list[dict]] = {}
    for gate, name, options in tqdm(runs, desc="select-trackers", unit="run", disable=not progress):
        m = evaluate(name, options, gate, data, config)
        row = {"tracker": name, "min_speed": gate[0], "min_motion": gate[1], "options": options,
               **{k: m[k] for k in ("MOTA", "HOTA", "IDS", "FP", "FN", "IDF1")}}
        log.append(row)
        rows.setdefault((gate, name), []).append(row)
    best = {key: choose(candidates, mota_tolerance) for key, candidates in rows.items()}
    main = pipeline_tracker(config, trackers)
    if ids_limit is not None:
        reference, ratio = ids_limit
        for gate in gates:
            best[(gate, main)] = choose(rows[(gate, main)], mota_tolerance, ratio * best[(gate, reference)]["IDS"])
    gate = max(gates, key=lambda g: best[(g, main)]["MOTA"])
    chosen = {name: best[(gate, name)]["options"] for name in trackers if best[(gate, name)]["options"]}
    return config.replace(min_speed=gate[0], min_motion=gate[1], trackers=chosen, tracker_options={}), log
