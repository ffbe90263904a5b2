"""``torchtrack scenario maneuver``: the maneuver paper's three experiments, all runs batched.

1. refinement of a stationary target's latitude/longitude (§3.1, Fig. 1–2);
2. a constant-velocity target (§3.2, Fig. 3–7);
3. a target maneuvering at scans 60 and 125, tracked by a plain Kalman filter and by the filter with
   χ² maneuver detection and reset (§3.3, §4.1, Fig. 8–9).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import torch

from torchtrack.config import load_sections, preset_path
from torchtrack.errors import TorchtrackError
from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter
from torchtrack.filters.kalman.maneuver import ManeuverDetectingKalmanFilter
from torchtrack.metrics.table import format_table
from torchtrack.models import ConstantPosition, ConstantVelocity, LinearPosition
from torchtrack.sim import maneuver as sim

DEFAULT_CONFIG = preset_path("maneuver")


def load_config(path: Path) -> dict:
    """Read and check the scenario YAML (sections ``stationary``, ``constant_velocity``, ``maneuver``, ``filter``)."""
    return load_sections(path, "maneuver")


def _rmse(err: torch.Tensor) -> float:
    """Root mean square of the Euclidean error ``(…, d)`` over everything else."""
    return float(err.pow(2).sum(-1).mean().sqrt())


def run_stationary(cfg: dict, runs: int, gen: torch.Generator) -> dict:
    seq = sim.stationary(cfg["scans"], runs, cfg["sigma"], gen)
    kf = KalmanFilter(ConstantPosition(2, q=1e-12, learnable=False), LinearPosition(2, 2, sigma=cfg["sigma"])).double()
    R = kf.measurement.noise_cov().to(seq.measurements)
    init = GaussianState(seq.measurements[0], R.expand(runs, 2, 2))
    res = kf.run(seq.measurements[1:], init, predict_first=True)
    est = torch.cat([seq.measurements[:1], res.mean])
    half = cfg["scans"] // 2
    return {"seq": seq, "estimate": est,
            "rmse_measured": _rmse(seq.measurements[half:] - seq.truth[half:]),
            "rmse_estimated": _rmse(est[half:] - seq.truth[half:]),
            "final_error": _rmse(est[-1] - seq.truth[-1])}


def fitted_kalman(fcfg: dict, sigma: float, params: Path | None = None) -> KalmanFilter:
    """The Kalman filter of the constant-velocity and maneuver experiments (CV, PWCA noise ``q``, position
    measurements ``sigma``); with ``params`` (a ``torchtrack tune`` file of a ``kalman`` filter with
    ``motion: cv``, ``noise: pwca``, ``ndim: 2`` and the same ``dt``) its ``motion.q`` and
    ``measurement.sigma`` are the fitted ones, loaded exactly (:func:`torchtrack.tuning.tune.load_params`)."""
    kf = KalmanFilter(ConstantVelocity(2, q=fcfg["q"], noise="pwca"), LinearPosition(2, sigma=sigma)).double()
    if params is not None:
        from torchtrack.tuning.config import load_params, read_params_file

        model = read_params_file(params, ("kalman",), "scenario maneuver").get("model") or {}
        got = {"motion": model.get("motion", "cv"), "noise": model.get("noise", "cwna"),
               "ndim": int(model.get("ndim", 2)), "dt": float(model.get("dt", 1.0))}
        want = {"motion": "cv", "noise": "pwca", "ndim": 2, "dt": float(fcfg["dt"])}
        if got != want:
            raise TorchtrackError(f"{params}: fitted with model {got}; the maneuver scenario's filter is {want}")
        load_params(kf, params)
    return kf


def _filters(fcfg: dict, sigma: float, params: Path | None = None
             ) -> tuple[ManeuverDetectingKalmanFilter, ManeuverDetectingKalmanFilter]:
    kf = fitted_kalman(fcfg, sigma, params)
    detecting = ManeuverDetectingKalmanFilter(kf, threshold=fcfg["threshold"])
    plain = ManeuverDetectingKalmanFilter(kf, threshold=fcfg["threshold"], reset=False)
    return plain, detecting


def run_constant_velocity(cfg: dict, fcfg: dict, runs: int, gen: torch.Generator, params: Path | None = None) -> dict:
    seq = sim.maneuvering(cfg["scans"], runs, cfg["speed"], [], [], 1, cfg["sigma"], cfg["sigma_a"],
                          fcfg["dt"], gen)
    plain, _ = _filters(fcfg, cfg["sigma"], params)
    res = plain.run(seq.measurements, fcfg["dt"])
    settle = 10
    return {"seq": seq, "result": res,
            "rmse_measured": _rmse(seq.measurements[settle:] - seq.truth[settle:, :, :2]),
            "rmse_estimated": _rmse(res.mean[settle:, :, :2] - seq.truth[settle:, :, :2]),
            "rmse_velocity": _rmse(res.mean[settle:, :, 2:] - seq.truth[settle:, :, 2:])}


def run_maneuver(cfg: dict, fcfg: dict, runs: int, gen: torch.Generator, params: Path | None = None) -> dict:
    seq = sim.maneuvering(cfg["scans"], runs, cfg["speed"], cfg["onsets"], cfg["turn_deg"], cfg["turn_scans"],
                          cfg["sigma"], cfg["sigma_a"], fcfg["dt"], gen)
    plain, detecting = _filters(fcfg, cfg["sigma"], params)
    res_plain = plain.run(seq.measurements, fcfg["dt"])
    res_det = detecting.run(seq.measurements, fcfg["dt"])
    scans = cfg["scans"]
    scan_no = torch.arange(1, scans + 1)
    in_window = torch.zeros(scans, dtype=torch.bool)
    rates, delays = [], []
    for onset in cfg["onsets"]:
        in_window |= (scan_no >= onset) & (scan_no < onset + cfg["window"])
        near = (scan_no >= onset) & (scan_no <= onset + fcfg["detection_delay"])
        hits = res_det.detected & near[:, None]
        detected = hits.any(0)
        rates.append(float(detected.double().mean()))
        first = torch.where(hits, scan_no[:, None], torch.full_like(hits, 10**9, dtype=torch.long)).amin(0)
        delays.append(float((first[detected] - onset).double().median()) if bool(detected.any()) else None)
    outside = ~in_window
    outside[:2] = False  # the first two scans initialise the filter and are never tested
    false_alarms = float(res_det.detected[outside].double().sum()) / (outside.sum() * runs) * 100
    rmse_kf, rmse_det = (_rmse(r.mean[in_window, :, :2] - seq.truth[in_window, :, :2]) for r in (res_plain, res_det))
    return {"seq": seq, "plain": res_plain, "detecting": res_det, "window": in_window,
            "detection_rate": rates, "median_detection_delay": delays,
            "false_alarms_per_100_scans": false_alarms,
            "rmse_position_kf": rmse_kf, "rmse_position_detecting_kf": rmse_det,
            "rmse_reduction": 1 - rmse_det / rmse_kf}


class ManeuverReport(NamedTuple):
    """The three experiments' results (the dicts of :func:`run_stationary`, :func:`run_constant_velocity` and
    :func:`run_maneuver`), the scenario config and the settings they ran with."""
    stationary: dict
    constant_velocity: dict
    maneuver: dict
    config: dict
    runs: int
    seed: int
    params: Path | None


def run_experiments(config: Path, runs: int, seed: int, params: Path | None = None) -> ManeuverReport:
    """All three experiments from the scenario YAML ``config``, ``runs`` Monte Carlo runs batched, one generator
    seeded with ``seed``; ``params``: a fitted-parameter file for the Kalman filter (:func:`fitted_kalman`)."""
    cfg = load_config(config)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        st = run_stationary(cfg["stationary"], runs, gen)
        cv = run_constant_velocity(cfg["constant_velocity"], cfg["filter"], runs, gen, params)
        mv = run_maneuver(cfg["maneuver"], cfg["filter"], runs, gen, params)
    return ManeuverReport(st, cv, mv, cfg, runs, seed, params)


def format_report(r: ManeuverReport) -> str:
    """The tables that ``torchtrack scenario maneuver`` prints."""
    st, cv, mv, cfg = r.stationary, r.constant_velocity, r.maneuver, r.config
    onsets = cfg["maneuver"]["onsets"]
    rows = [[f"scan {o}", mv["detection_rate"][i],
             "-" if mv["median_detection_delay"][i] is None else f"{mv['median_detection_delay'][i]:.0f}"]
            for i, o in enumerate(onsets)]
    return "\n".join([
        f"Maneuver paper, {r.runs} Monte Carlo runs (seed {r.seed})\n",
        format_table(["experiment", "RMSE measured", "RMSE estimated", "note"], [
            ["stationary (arcsec)", st["rmse_measured"], st["rmse_estimated"],
             f"final error {st['final_error']:.3f}"],
            ["constant velocity (m)", cv["rmse_measured"], cv["rmse_estimated"],
             f"velocity RMSE {cv['rmse_velocity']:.3f} m/s"],
        ]),
        "",
        format_table(["maneuver onset", f"detected within {cfg['filter']['detection_delay']} scans",
                      "median delay (scans)"], rows),
        f"\nfalse alarms per 100 scans outside maneuvers: {mv['false_alarms_per_100_scans']:.3f}",
        format_table(["filter", "position RMSE over maneuver windows (m)"], [
            ["Kalman filter", mv["rmse_position_kf"]],
            ["with maneuver detection", mv["rmse_position_detecting_kf"]],
        ]),
        f"RMSE reduction: {100 * mv['rmse_reduction']:.1f}%",
    ])


def report_json(r: ManeuverReport) -> dict:
    """The numbers of ``--json``."""
    mv = r.maneuver
    return {
        "maneuver_onsets": r.config["maneuver"]["onsets"],
        **{k: mv[k] for k in ("detection_rate", "median_detection_delay", "false_alarms_per_100_scans",
                              "rmse_position_kf", "rmse_position_detecting_kf", "rmse_reduction")},
        "stationary": {k: r.stationary[k] for k in ("rmse_measured", "rmse_estimated", "final_error")},
        "constant_velocity": {k: r.constant_velocity[k] for k in ("rmse_measured", "rmse_estimated", "rmse_velocity")},
        "threshold": r.config["filter"]["threshold"],
        "runs": r.runs,
        "seed": r.seed,
        "params": None if r.params is None else str(r.params),
    }
