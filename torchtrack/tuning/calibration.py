"""``torchtrack calibrate`` as one call: the sensor's EM (:mod:`torchtrack.tuning.calibrate`), the decisions
(:mod:`torchtrack.tuning.decisions`), the record written as ``calibration.json`` and the loss plot."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchtrack.io.mot import MOTData
from torchtrack.io.outputs import save_figure
from torchtrack.tuning.calibrate import Calibration, calibrate_sensor, detection_frames
from torchtrack.tuning.decisions import bootstrap_decisions, gmphd_section, pseudo_truth, tracker_sections


@dataclass
class CalibrationResult:
    """The fitted model (:class:`Calibration`), the decisions, the bootstrap's scores and the trackers'
    ``track --config`` sections."""

    calibration: Calibration
    decisions: dict[str, Any]
    bootstrap: list[dict]
    sections: dict[str, Any]
    seconds: float

    def record(self, source: str) -> dict[str, Any]:
        """The contents of ``calibration.json``."""
        c = self.calibration
        return {"detections": source, "frames": list(c.frames), "detections_used": c.detections,
                "velocities": c.velocities, "region": list(c.region), "tracks_used": c.tracks,
                "values": c.values, "stderr": c.stderr, "loglik_before": c.loglik_before,
                "loglik_after": c.loglik_after, "iterations": c.iterations, "decisions": self.decisions,
                "bootstrap": self.bootstrap, "seconds": self.seconds}


def calibrate(det: MOTData, frames: tuple[int, int] | None = None, velocity: bool | None = None, seed: int = 0,
              source: str = "detections", progress: Callable[[str], None] | None = None) -> CalibrationResult:
    """Calibrate the trackers to the sensor of ``det`` (frames ``A..B`` inclusive, None: all) without truth;
    ``velocity`` as :func:`~torchtrack.tuning.calibrate.detection_frames`; ``seed`` drives the bootstrap."""
    t0 = time.perf_counter()
    data = detection_frames(det, frames, velocity, source)
    cal, tracks, mean = calibrate_sensor(data, gmphd_section, progress=progress)
    decisions, log = bootstrap_decisions(cal, pseudo_truth(tracks, mean, data.first), seed, progress)
    return CalibrationResult(cal, decisions, log, tracker_sections(cal, decisions), time.perf_counter() - t0)


def plot_calibration(result: CalibrationResult, path: str | Path) -> Path:
    """The M-steps' negative log-likelihood per candidate pair over their L-BFGS evaluations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(range(len(result.calibration.trace)), result.calibration.trace, lw=1)
    ax.set_xlabel("L-BFGS evaluation (all M-steps in turn)")
    ax.set_ylabel("negative log-likelihood per candidate pair")
    ax.set_title("torchtrack calibrate")
    return save_figure(fig, path, dpi=100)
