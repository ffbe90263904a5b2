"""Does a calibration describe the sensor, or did the fit fail? (docs/calibrate.md, "When the fit fails")

A failed fit is the E-step tracking clutter: on a harsh sensor without velocities (p_D 0.6, σ 3.5 px, 250 false
detections a frame) the tracker's early tracks follow false detections, the M-step then explains most detections
near them as clutter (fitted p_D about a third of the true one, σ 40 % low), every track's ``q`` runs to the
top of its grid, and the bootstrap's best tracker reports nothing. Each sign is checked on its own:

- ``q`` at either end of :data:`~torchtrack.tuning.calibrate.Q_GRID`;
- p_D under :data:`P_D_RATIO` of the share of the frames inside the tracks' lives with a detection (the two
  agree within a few percent on sensors the tracker follows), or σ / σ_v at their bounds;
- the bootstrap's best MOTA under :data:`MIN_BOOTSTRAP_MOTA` (the fitted model itself says nothing is trackable);
- the calibrated enhanced GM-PHD reporting no track on the calibration frames where the built-in one reports
  some.

A standard error that is not finite is only a warning (:func:`fit_warnings`): it comes with sound fits too,
where the likelihood is so peaked (p_D near 1, σ under a pixel) that its Hessian is not positive definite in
floating point.
"""

from __future__ import annotations

import math

from torchtrack.tuning.calibrate import Q_GRID, Calibration, DetectionFrames, run_tracker
from torchtrack.tuning.sensor_likelihood import LOG_NOISE

P_D_RATIO = 0.5
MIN_BOOTSTRAP_MOTA = 0.05
CHECK_FRAMES = 150
"""The last frames of the calibration window on which the calibrated and the built-in trackers are run."""


def fit_problems(cal: Calibration, bootstrap_mota: float | None = None) -> list[str]:
    """The signs of a failed fit in ``cal`` and (where given) the bootstrap's best MOTA (module docstring), one
    phrase each."""
    v = cal.values
    problems = []
    if v["q"] >= float(Q_GRID[-1]) * 0.999 or v["q"] <= float(Q_GRID[0]) * 1.001:
        problems.append(f"q {v['q']:.3g} at an end of its grid")
    if v["p_detection"] < P_D_RATIO * cal.detected_share:
        problems.append(f"p_D {v['p_detection']:.3g} under half the tracks' detected share "
                        f"{cal.detected_share:.3g}")
    low, high = (math.exp(b) for b in LOG_NOISE)
    for key in ("sigma", "velocity_sigma"):
        if key in v and not low * 1.01 < v[key] < high * 0.99:
            problems.append(f"{key} {v[key]:.3g} at its bound")
    if bootstrap_mota is not None and bootstrap_mota < MIN_BOOTSTRAP_MOTA:
        problems.append(f"bootstrap MOTA {bootstrap_mota:.3f} under {MIN_BOOTSTRAP_MOTA}")
    return problems


def fit_warnings(cal: Calibration) -> list[str]:
    """What in ``cal`` deserves a look but does not fail it (module docstring)."""
    bad = sorted(key for key, err in cal.stderr.items() if not math.isfinite(err))
    return [f"standard error of {', '.join(bad)} not finite"] if bad else []


def tracks_nothing(data: DetectionFrames, config: dict, built_in: dict) -> bool:
    """Whether the enhanced GM-PHD with ``config`` reports no track on the last :data:`CHECK_FRAMES` frames of
    ``data`` while the one with ``built_in`` options reports some."""
    tail = tail_frames(data, CHECK_FRAMES)
    return not run_tracker(tail, config) and bool(run_tracker(tail, built_in))


def tail_frames(data: DetectionFrames, frames: int) -> DetectionFrames:
    """The last ``frames`` frames of ``data``."""
    cut = max(len(data.positions) - frames, 0)
    return DetectionFrames(data.first + cut, data.last, data.positions[cut:],
                           None if data.velocities is None else data.velocities[cut:], data.region)
