"""``torchtrack bench calibrate``: the calibration from detections alone against a black-box search with truth.

Workload: detections simulated from a truth file (``simulate_detections``: p_D, σ, clutter, velocity σ over the
image), training frames ``A..B`` and held-out frames ``C..D``. Measured in the same run:

* **ours** — :func:`torchtrack.tuning.calibration.calibrate` on the training detections, no truth;
* **reference** — Optuna's TPE sampler (seeded) maximising the enhanced GM-PHD's MOTA on the training frames
  *with the truth*, over :data:`SPACE`, for ``trials`` tracker runs (default: as many tracker passes over the
  training frames as the calibration made, counted in frames);
* **defaults** — the built-in options.

Each configuration then tracks the held-out frames from empty and is scored (CLEAR-MOT at 10 px, HOTA), and so do
the GLMB and the PMB with their calibrated sections and with their built-in options. Optuna
is an optional benchmark dependency (``pip install torchtrack-mtt[bench]``); without it the reference is skipped
with a message.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from torchtrack.bench._timing import BenchResult
from torchtrack.io.mot import MOTData
from torchtrack.pipeline.api import track
from torchtrack.sim.detections import simulate_detections
from torchtrack.tuning.calibration import calibrate
from torchtrack.tuning.decisions import MODEL_SEARCH, SEARCH

SPACE: dict[str, tuple[float, float, bool]] = {
    "filter.sigma": (0.5, 6.0, True), "filter.p_detection": (0.3, 0.99, False),
    "filter.clutter_density": (1e-5, 3e-3, True), "filter.velocity_sigma": (0.5, 6.0, True),
    "filter.q": (0.05, 20.0, True), "birth.birth_weight": (1e-3, 0.2, True),
    "coast_threshold": (0.01, 0.5, True), "filter.extract_threshold": (0.3, 0.9, False),
}
"""The 8 enhanced GM-PHD options of the Optuna search: (low, high, log scale)."""


def _window(data: MOTData, first: int, last: int) -> MOTData:
    return data.select((data.frame >= first) & (data.frame <= last))


def held_out(det: MOTData, gt: MOTData, config: dict | None, tracker: str = "gmphd") -> dict[str, float]:
    """MOTA, HOTA, IDS of ``tracker`` with ``config`` (its section, None: defaults) on ``det``, every object of
    ``gt`` a target (the detections are simulated from all of them, parked vehicles too)."""
    result = track(detections=det, gt=gt, tracker=tracker, config={tracker: config} if config else None,
                   score="all")
    m = result.metrics
    return {"MOTA": m["MOTA"], "HOTA": m["HOTA"], "IDS": m["IDS"]}


def _nested(flat: dict[str, Any]) -> dict:
    out: dict = {}
    for key, value in flat.items():
        head, _, tail = key.partition(".")
        if tail:
            out.setdefault(head, {})[tail] = value
        else:
            out[head] = value
    return out


def optuna_search(det: MOTData, gt: MOTData, trials: int, seed: int,
                  progress: Callable[[str], None] | None = None) -> dict | None:
    """The best gmphd section found by TPE in ``trials`` runs on ``det`` scored against ``gt``; None without
    Optuna."""
    try:
        import optuna
    except ImportError:
        return None
    optuna.logging.set_verbosity(optuna.logging.WARNING)

    def objective(trial: Any) -> float:
        flat = {k: trial.suggest_float(k, lo, hi, log=log) for k, (lo, hi, log) in SPACE.items()}
        mota = held_out(det, gt, _nested(flat))["MOTA"]
        if progress is not None:
            progress(f"optuna trial {trial.number + 1}/{trials}: MOTA {mota:.3f}")
        return mota

    study = optuna.create_study(direction="maximize", sampler=optuna.samplers.TPESampler(seed=seed))
    study.optimize(objective, n_trials=trials)
    return _nested(study.best_params)


def measure(gt: MOTData, pd: float, sigma: float, clutter: float, velocity_sigma: float | None,
            image_size: tuple[float, float], train: tuple[int, int], test: tuple[int, int],
            trials: int | None = None, seed: int = 0, progress: Callable[[str], None] | None = None) -> BenchResult:
    """The comparison of the module docstring; ``trials`` None: the calibration's tracker passes."""
    det = simulate_detections(gt, pd, sigma, clutter, image_size, velocity_sigma,
                              torch.Generator().manual_seed(seed)).detections
    train_det, train_gt = _window(det, *train), _window(gt, *train)
    test_det, test_gt = _window(det, *test), _window(gt, *test)
    t0 = time.perf_counter()
    result = calibrate(train_det, train, None, seed, progress=progress)
    cal_s = time.perf_counter() - t0
    frames = train[1] - train[0] + 1
    passes = result.tracker_frames
    n_trials = trials if trials is not None else max(1, math.ceil(passes / frames))
    t0 = time.perf_counter()
    best = optuna_search(train_det, train_gt, n_trials, seed, progress)
    ref_s = time.perf_counter() - t0
    calibrated = held_out(test_det, test_gt, result.sections["gmphd"])
    defaults = held_out(test_det, test_gt, None)
    reference = held_out(test_det, test_gt, best) if best is not None else None
    others = {name: {"calibrated": held_out(test_det, test_gt, result.sections[name] or None, name)["MOTA"],
                     "defaults": held_out(test_det, test_gt, None, name)["MOTA"]} for name in ("glmb", "pmb")}
    extra = {"calibrated_mota": calibrated["MOTA"], "calibrated_hota": calibrated["HOTA"],
             "defaults_mota": defaults["MOTA"], "defaults_hota": defaults["HOTA"],
             "reference_mota": reference["MOTA"] if reference else None,
             "reference_hota": reference["HOTA"] if reference else None,
             "calibrate_seconds": cal_s, "others_mota": others,
             "reference_seconds": ref_s if best is not None else None,
             "reference_trials": n_trials if best is not None else 0, "tracker_frames_calibrate": passes,
             "fitted": result.calibration.values if result.calibration else None,
             "status": result.status, "problems": result.problems, "decisions": result.decisions, "optuna_best": best,
             "sensor": {"pd": pd, "sigma": sigma, "clutter": clutter, "velocity_sigma": velocity_sigma},
             "train": list(train), "test": list(test), "seed": seed,
             "searched": [key for key, _ in SEARCH + MODEL_SEARCH]}
    workload = (f"p_D {pd:g}, σ {sigma:g} px, clutter {clutter:g}/frame"
                + (f", velocity σ {velocity_sigma:g}" if velocity_sigma else "")
                + f"; calibrate on frames {train[0]}-{train[1]}, held out {test[0]}-{test[1]}")
    return BenchResult(workload, 1.0 / cal_s, f"Optuna TPE with truth, {n_trials} trials",
                       1.0 / ref_s if best is not None else float("nan"), "calibrations", extra)


def format_report(r: BenchResult) -> str:
    """The held-out scores and wall times."""
    from torchtrack.metrics.table import format_table

    e = r.extra

    def cell(x: float | None) -> str:
        return "—" if x is None else f"{x:.3f}"

    rows = [["calibrate (no truth)", cell(e["calibrated_mota"]), cell(e["calibrated_hota"]),
             f"{e['calibrate_seconds']:.1f}"],
            [f"Optuna TPE with truth ({e['reference_trials']} trials)", cell(e["reference_mota"]),
             cell(e["reference_hota"]), "—" if e["reference_seconds"] is None else f"{e['reference_seconds']:.1f}"],
            ["built-in defaults", cell(e["defaults_mota"]), cell(e["defaults_hota"]), "—"]]
    lines = [f"workload: {r.workload}", f"calibration status: {e['status']}",
             format_table(["configuration", "held-out MOTA", "HOTA", "seconds"], rows)]
    lines.append("held-out MOTA, calibrated / built-in: " + ", ".join(
        f"{name} {x['calibrated']:.3f} / {x['defaults']:.3f}" for name, x in e["others_mota"].items()))
    if e["reference_mota"] is None:
        lines.append("Optuna is not installed (pip install torchtrack-mtt[bench]): the reference was skipped")
    return "\n".join(lines)


def as_image_size(values: list[float] | None, gt: MOTData) -> tuple[float, float]:
    """``--image-size`` or just covering the truth."""
    if values is not None:
        return float(values[0]), float(values[1])
    c = gt.centers()
    return float(np.floor(c[:, 0].max()) + 1), float(np.floor(c[:, 1].max()) + 1)
