"""``torchtrack calibrate`` as one call: the sensor's EM (:mod:`torchtrack.tuning.calibrate`), its checks
(:mod:`torchtrack.tuning.fit_check`: a failed fit is fitted again from a stricter start, and where that fails too
the built-in options are written), the bootstrap's search (:mod:`torchtrack.tuning.decisions`), the record
written as ``calibration.json`` and the loss plot."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from torchtrack.filters.trackers.options import POSITIONS_ONLY
from torchtrack.io.mot import MOTData
from torchtrack.io.outputs import save_figure, write_json, write_yaml
from torchtrack.tuning.calibrate import (
    ITERATIONS,
    Calibration,
    DetectionFrames,
    NoTracks,
    calibrate_sensor,
    detection_frames,
    initial_values,
)
from torchtrack.tuning.decisions import (
    BOOTSTRAP_FRAMES,
    bootstrap_decisions,
    gmphd_section,
    merged,
    pseudo_truth,
    tracker_sections,
)
from torchtrack.tuning.fit_check import CHECK_FRAMES, fit_problems, fit_warnings, tracks_nothing
from torchtrack.tuning.gmphd import quiet_caps

STARTS: tuple[dict[str, Any], ...] = ({}, {"confirm_new": 4, "birth_weight": 0.005})
"""The E-step tracker's decisions of the first start (the rules' own) and of the second, tried where the first
fit fails (:mod:`torchtrack.tuning.fit_check`): a stricter tracker, whose tracks follow fewer false detections."""
BUILT_IN_MARGIN = 5
"""Errors on the bootstrap's frames by which a calibrated tracker (the enhanced GM-PHD, the GLMB, the PMB) must beat
its built-in options to replace them (a MOTA of ``5 / points`` more): a handful of errors either way is within the
bootstrap's resolution, and the built-in options were chosen on validation data of their own. On a 20-frame video
window this is about 0.015 of MOTA, on 150 frames of WPAFB scale about 0.0004."""
BUILT_IN = {"gmphd": {}, "labelled-gmphd": {}, "glmb": {}, "pmb": {}}
"""The sections written when every start fails: each tracker's built-in options (the enhanced GM-PHD's with the
measured clutter density and, without velocities, σ: :func:`fallback_section`)."""


@dataclass
class CalibrationResult:
    """The fitted model (:class:`Calibration`; None where no start confirmed a track), the decisions, the
    bootstrap's scores, the trackers' ``track --config`` sections, and the verdict: ``status`` ``ok`` (the
    first start), ``retried`` (the second) or ``defaults`` (every start failed: the sections are the built-in
    options), the frames the trackers stepped through over every start (``tracker_frames``: the cost in
    tracker passes), the ``problems`` found at each start, ``message``, the verdict in one line, and the
    ``warnings`` of the fit kept (:func:`~torchtrack.tuning.fit_check.fit_warnings`)."""

    calibration: Calibration | None
    decisions: dict[str, Any]
    bootstrap: list[dict]
    sections: dict[str, Any]
    seconds: float
    status: str = "ok"
    tracker_frames: int = 0
    problems: list[list[str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    message: str = "the fit passed its checks"

    def write(self, folder: Path, source: str) -> dict[str, Path]:
        """``track.yaml``, ``calibration.json`` and ``loss.png`` into ``folder``; returns them by kind
        (``config``, ``calibration``, ``loss``)."""
        c = self.calibration
        window = f"frames {c.frames[0]}-{c.frames[1]}" if c is not None else "no track confirmed"
        files = {"config": folder / "track.yaml", "calibration": folder / "calibration.json",
                 "loss": folder / "loss.png"}
        write_yaml(files["config"], self.sections,
                   header=f"# torchtrack calibrate on {source}, {window}; status {self.status}\n")
        write_json(files["calibration"], self.record(source))
        plot_calibration(self, files["loss"])
        return files

    def record(self, source: str) -> dict[str, Any]:
        """The contents of ``calibration.json``."""
        verdict = {"status": self.status, "message": self.message, "problems": self.problems,
                   "warnings": self.warnings}
        c = self.calibration
        if c is None:
            return {"detections": source, **verdict, "decisions": self.decisions, "seconds": self.seconds}
        return {"detections": source, **verdict, "frames": list(c.frames), "detections_used": c.detections,
                "velocities": c.velocities, "region": list(c.region), "tracks_used": c.tracks,
                "detected_share": c.detected_share, "values": c.values, "stderr": c.stderr,
                "loglik_before": c.loglik_before, "loglik_after": c.loglik_after, "iterations": c.iterations,
                "decisions": self.decisions, "bootstrap": self.bootstrap, "seconds": self.seconds}


def calibrate(det: MOTData, frames: tuple[int, int] | None = None, velocity: bool | None = None, seed: int = 0,
              source: str = "detections", progress: Callable[[str], None] | None = None,
              base: dict | None = None) -> CalibrationResult:
    """Calibrate the trackers to the sensor of ``det`` (frames ``A..B`` inclusive, None: all) without truth;
    ``velocity`` as :func:`~torchtrack.tuning.calibrate.detection_frames`; ``seed`` drives the bootstrap.
    ``base``: the enhanced GM-PHD's options that the calibrated ones go over and that count as its built-in
    ones (default: none, the tracker's own; the video pipeline's are its ``trackers.gmphd``).
    Each start of :data:`STARTS` is tried until one passes :func:`~torchtrack.tuning.fit_check.fit_problems`;
    where none does, the sections are the built-in options (``status`` ``defaults``; on a detection file, with
    the measured clutter density and, without velocities, σ: :func:`fallback_section`)."""
    with quiet_caps():          # mis-specified trackers fill the GM-PHD's component cap on every frame
        return _calibrate(detection_frames(det, frames, velocity, source), seed, progress, base)


def _calibrate(data: DetectionFrames, seed: int, progress: Callable[[str], None] | None, base: dict | None
               ) -> CalibrationResult:
    t0 = time.perf_counter()
    problems: list[list[str]] = []
    last = None
    window = len(data.positions)
    stepped = 0
    for n, decisions in enumerate(STARTS):
        stepped += window * ITERATIONS
        try:
            cal, tracks, mean = calibrate_sensor(data, partial(_e_step, decisions), progress=progress)
        except NoTracks as e:
            problems.append([str(e).removeprefix("calibration: ")])
            continue
        found = fit_problems(cal)
        if found:                   # the fit's own signs: no bootstrap search on a failed fit
            problems.append(found)
            last = (cal, None)
            continue
        boot = bootstrap_decisions(cal, pseudo_truth(tracks, mean, data.first), seed, progress, base)
        stepped += len(boot.log) * min(BOOTSTRAP_FRAMES, window) + 2 * min(CHECK_FRAMES, window)
        sections = tracker_sections(cal, boot.decisions, boot.values)
        sections["gmphd"] = merged(base or {}, sections["gmphd"])
        margin = BUILT_IN_MARGIN / max(boot.points, 1)
        kept = [name for name, (calibrated, built_in) in boot.against_built_in.items()
                if built_in > calibrated - margin]                   # the calibrated options do not track better
        for name in kept:
            sections[name] = dict(base or {}) if name == "gmphd" else {}
        found = fit_problems(cal, boot.mota)
        if not found and tracks_nothing(data, sections["gmphd"], base or {}):
            found.append("the calibrated tracker reports no track where the built-in one does")
        problems.append(found)
        last = (cal, boot)
        if not found:
            status = "ok" if n == 0 else "retried"
            message = ("the fit passed its checks" if n == 0 else
                       f"the first fit failed ({'; '.join(problems[0])}); the second start passed its checks")
            if kept:
                message += (f"; {', '.join(kept)} keep{'s' if len(kept) == 1 else ''} the built-in options, which "
                            "track the simulated frames as well")
            return CalibrationResult(cal, boot.decisions, boot.log, sections, time.perf_counter() - t0, status,
                                     stepped, problems, fit_warnings(cal), message)
    found = list(dict.fromkeys(p for attempt in problems for p in attempt))
    cal, boot = last if last is not None else (None, None)
    if base is None:
        start = initial_values(data)
        kappa = (cal.values if cal is not None else start)["clutter_density"]
        gmphd = fallback_section(kappa, start["sigma"], data.velocities is not None)
        held = f"the built-in options with the measured clutter density {kappa:.3g}"
        if data.velocities is None:
            held += f" and σ {start['sigma']:.3g} from consecutive frames"
    else:
        gmphd, held = dict(base), "the built-in options"
    message = f"the fit failed at every start ({'; '.join(found)}): track.yaml holds {held}"
    return CalibrationResult(cal, boot.decisions if boot else {}, boot.log if boot else [],
                             {**BUILT_IN, "gmphd": gmphd}, time.perf_counter() - t0, "defaults", stepped, problems,
                             message=message)


def fallback_section(clutter_density: float, sigma: float, velocities: bool) -> dict[str, Any]:
    """The enhanced GM-PHD's section after a failed fit on a detection file: its built-in options with what is
    measured whatever the tracks: the clutter density where no track passes and, without velocities, the
    position noise from consecutive frames (:func:`~torchtrack.tuning.calibrate.initial_sigma`). That σ takes in
    the truth's jitter and some clutter, so it is wider than the sensor's; on four harsh validation sensors
    without velocities it raised the held-out MOTA by 0.03 to 0.09 over the built-in σ (docs/calibrate.md)."""
    if velocities:
        return {"filter": {"clutter_density": clutter_density}}
    return {"positions_only": merged(POSITIONS_ONLY, {"filter": {"clutter_density": clutter_density,
                                                                "sigma": sigma}})}


def _e_step(decisions: dict[str, Any], values: dict[str, float]) -> dict[str, Any]:
    return gmphd_section(values, decisions)


def plot_calibration(result: CalibrationResult, path: str | Path) -> Path:
    """The M-steps' negative log-likelihood per candidate pair over their L-BFGS evaluations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    trace = result.calibration.trace if result.calibration is not None else []
    ax.plot(range(len(trace)), trace, lw=1)
    ax.set_xlabel("L-BFGS evaluation (all M-steps in turn)")
    ax.set_ylabel("negative log-likelihood per candidate pair")
    ax.set_title("torchtrack calibrate")
    return save_figure(fig, path, dpi=100)
