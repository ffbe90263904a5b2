"""``torchtrack scenario pedestrian``: feature tracking from a vehicle with uncertain position (PMB paper, Sec. 5).

A simulated counterpart of the paper's recording: a vehicle standing still, a static feature at about
50 m, a pedestrian who enters at step 208, walks away, rests at about 10, 20 and 30 m and leaves at
step 1330; T_s = 0.1 s, 1461 steps; GNSS fixes of the vehicle with variance 0.9216 m², relative (V2F)
measurements with variance 0.42 m², p_D = 0.9, 10 false alarms per scan uniform on (−200 m, 200 m)².

Three TOMB/P filters track the features in the global frame from the same data (all runs batched):
``naive`` (the sensor is where the GNSS fix says), ``inflated`` (the same, the V2F noise increased by the
GNSS covariance: the paper's variance inflation), ``joint`` (the joint vehicle–feature filter). Each is
scored per step by OSPA (c = 20 m, p = 2) against the true feature positions (paper Fig. 4), averaged
over steps and runs (the paper: 0.87, 0.99, 2.61).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import torch
from tqdm import tqdm

from torchtrack.config import load_sections, preset_path
from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb.filter import PMBFilter
from torchtrack.filters.pmb.sensor import JointSensorPMB, SensorState, v2f_update
from torchtrack.metrics.ospa import ospa
from torchtrack.metrics.table import format_table
from torchtrack.models import ConstantVelocity, LinearPosition
from torchtrack.threads import torch_threads

DEFAULT_CONFIG = preset_path("pedestrian")
VARIANTS = ("joint", "inflated", "naive")
EXTRA_VARIANTS = ("inflated_kf",)   # variance inflation around a Kalman-filtered sensor state
PAPER_OSPA = {"joint": 0.87, "inflated": 0.99, "naive": 2.61}


def load_config(path: Path) -> dict:
    return load_sections(path, "pedestrian")


class Truth(NamedTuple):
    vehicle: torch.Tensor   # (T, 4) [x, y, vx, vy]
    features: torch.Tensor  # (T, F, 4)
    present: torch.Tensor   # (T, F) bool


class Recording(NamedTuple):
    gnss: torch.Tensor      # (T, R, 2) GNSS fixes of the vehicle position
    z: torch.Tensor         # (T, R, M, 2) V2F measurements, feature minus vehicle (padded)
    mask: torch.Tensor      # (T, R, M) bool


def pedestrian_track(scene: dict, steps: int) -> torch.Tensor:
    """x position of the pedestrian per step (NaN when absent): walk, rest at each stop, walk away."""
    ped = scene["pedestrian"]
    dt, v = scene["dt"], ped["speed"]
    x = torch.full((steps,), float("nan"), dtype=torch.float64)
    t, pos = ped["enter"], float(ped["start_x"])
    plan = [(float(stop), int(rest)) for stop, rest in ped["rests"]]
    while t < min(ped["leave"], steps):
        if plan and pos >= plan[0][0]:
            stop, rest = plan.pop(0)
            end = min(t + rest, ped["leave"], steps)
            x[t:end] = stop
            t, pos = end, stop
            continue
        x[t] = pos
        pos = min(pos + v * dt, plan[0][0]) if plan else pos + v * dt
        t += 1
    return x


def make_truth(scene: dict, steps: int) -> Truth:
    vehicle = torch.tensor([*scene["vehicle"], 0.0, 0.0], dtype=torch.float64).expand(steps, 4)
    static = torch.tensor([*scene["static_feature"], 0.0, 0.0], dtype=torch.float64).expand(steps, 4)
    px = pedestrian_track(scene, steps)
    present = ~torch.isnan(px)
    vx = torch.nan_to_num(torch.diff(px, append=px[-1:]) / scene["dt"])     # forward difference, 0 at the end
    ped = torch.stack([torch.nan_to_num(px), torch.full_like(px, scene["pedestrian"]["y"]), vx,
                       torch.zeros_like(px)], -1)
    return Truth(vehicle, torch.stack([static, ped], 1), torch.stack([torch.ones_like(present), present], 1))


def simulate(scene: dict, truth: Truth, runs: int, gen: torch.Generator) -> Recording:
    """GNSS fixes and V2F scans (detections with p_D, Gaussian noise, Poisson clutter), all runs at once."""
    T, F = truth.present.shape
    f64 = torch.float64
    gnss = truth.vehicle[:, None, :2] + scene["gnss_var"] ** 0.5 * torch.randn(T, runs, 2, generator=gen, dtype=f64)
    detected = truth.present[:, None, :] & (torch.rand(T, runs, F, generator=gen, dtype=f64) < scene["p_detection"])
    rel = (truth.features[:, :, :2] - truth.vehicle[:, None, :2])[:, None]
    z_det = rel + scene["v2f_var"] ** 0.5 * torch.randn(T, runs, F, 2, generator=gen, dtype=f64)
    counts = torch.poisson(torch.full((T, runs), float(scene["clutter_rate"]), dtype=f64), generator=gen).long()
    C = int(counts.max()) if counts.numel() else 0
    z_clut = (2 * torch.rand(T, runs, C, 2, generator=gen, dtype=f64) - 1) * scene["clutter_half_width"]
    clut_mask = torch.arange(C).expand(T, runs, C) < counts.unsqueeze(-1)
    return Recording(gnss, torch.cat([z_det, z_clut], 2), torch.cat([detected, clut_mask], 2))


def build_filter(fcfg: dict, scene: dict, p_survival: float) -> PMBFilter:
    prior_cov = torch.diag(torch.tensor(fcfg["prior_std"], dtype=torch.float64) ** 2)
    return PMBFilter(
        ConstantVelocity(2, q=fcfg["feature_q"], learnable=False),
        LinearPosition(2, sigma=scene["v2f_var"] ** 0.5, learnable=False),
        p_survival=p_survival, p_detection=fcfg["p_detection"],
        clutter_intensity=scene["clutter_rate"] / (2 * scene["clutter_half_width"]) ** 2,
        birth_weight=fcfg["birth_weight"], birth_mean=torch.zeros(4, dtype=torch.float64), birth_cov=prior_cov,
        capacity=fcfg["capacity"], poisson_capacity=fcfg["poisson_capacity"], gate=fcfg["gate"],
        lbp_iterations=fcfg["lbp_iterations"], lbp_tol=fcfg["lbp_tol"], prune_existence=fcfg["prune_existence"],
        estimate_threshold=fcfg["estimate_threshold"], learnable=False).double()


class Run(NamedTuple):
    position: torch.Tensor  # (T, R, N, 2) estimated feature positions (global frame)
    mask: torch.Tensor      # (T, R, N) bool, reported
    label: torch.Tensor     # (T, R, N)
    sensor: torch.Tensor    # (T, R, 2) the sensor position the filter used


@torch.no_grad()
def run_variant(variant: str, filt: PMBFilter, rec: Recording, cfg: dict, progress: bool = True) -> Run:
    """Run one of ``VARIANTS`` or ``EXTRA_VARIANTS`` over the whole recording, all runs batched.

    ``inflated`` puts the sensor at the GNSS fix and inflates the V2F noise by the GNSS covariance (the
    paper's experiment); ``inflated_kf`` uses the mean and covariance ``Σ_x`` of a Kalman filter on the
    GNSS fixes instead (the paper's Sec. 3.4 wording), the joint filter without its V2F vehicle update.
    """
    scene, fcfg = cfg["scene"], cfg["filter"]
    T, R = rec.gnss.shape[:2]
    dt = scene["dt"]
    state = filt.init_state((R,), undetected_weight=fcfg["undetected_weight"])
    gnss_cov = scene["gnss_var"] * torch.eye(2, dtype=torch.float64).expand(R, 2, 2)
    joint = JointSensorPMB(filt, ConstantVelocity(2, q=fcfg["vehicle_q"], learnable=False).double(),
                           gnss_sigma=scene["gnss_var"] ** 0.5)
    init_var = torch.tensor(fcfg["vehicle_init_var"], dtype=torch.float64)
    sensor = SensorState(torch.cat([rec.gnss[0], torch.zeros(R, 2, dtype=torch.float64)], -1),
                         torch.diag(init_var).expand(R, 4, 4).clone())
    steps = []
    for t in tqdm(range(T), desc=f"pedestrian {variant}", disable=not progress, leave=False):
        if variant in ("joint", "inflated_kf"):
            if t > 0:
                sensor, state = joint.predict(sensor, state, dt)
                sensor = joint.gnss_update(sensor, rec.gnss[t])
            else:
                state = filt.predict(state, dt)
            if variant == "joint":
                sensor, state, _ = joint.v2f_update(sensor, state, rec.z[t], rec.mask[t])
            else:
                state, _ = v2f_update(filt, state, rec.z[t], rec.mask[t], sensor.mean, sensor.cov)
            used = sensor.mean[:, :2]
        else:
            state = filt.predict(state, dt)
            cov = gnss_cov if variant == "inflated" else None
            state, _ = v2f_update(filt, state, rec.z[t], rec.mask[t], rec.gnss[t], cov)
            used = rec.gnss[t]
        est = filt.estimate(state)
        steps.append((est.mean[..., :2], est.mask, est.label, used))
    return Run(*(torch.stack(t) for t in zip(*steps)))


def ospa_per_step(truth: Truth, run: Run, c: float, p: float) -> torch.Tensor:
    """OSPA ``(T, R)`` between the true and the reported feature positions."""
    T, R = run.mask.shape[:2]
    X = truth.features[:, None, :, :2].expand(T, R, -1, 2)
    xm = truth.present[:, None, :].expand(T, R, -1)
    return ospa(X, run.position, c=c, p=p, x_mask=xm, y_mask=run.mask).total


class PedestrianReport(NamedTuple):
    """Every variant's run over the same simulated recording and its OSPA against the truth."""
    truth: Truth
    variants: dict[str, Run]             # VARIANTS + EXTRA_VARIANTS
    ospa_per_step: dict[str, torch.Tensor]   # (T,) mean over runs
    mean_ospa: dict[str, float]
    config: dict
    runs: int
    steps: int
    p_survival: float
    seed: int


def run_variants(config: Path, runs: int, seed: int, *, steps: int | None = None, p_survival: float | None = None,
                 threads: int = 1, progress: bool = True) -> PedestrianReport:
    """Simulate ``runs`` recordings of the scenario YAML ``config`` (``steps`` long; None: the config's) and run
    every variant on them, on ``threads`` torch threads; ``p_survival`` None: the config's; ``progress``: a bar per
    variant."""
    with torch_threads(threads):
        cfg = load_config(config)
        scene, fcfg = cfg["scene"], cfg["filter"]
        steps = scene["steps"] if steps is None else steps
        if steps < 1:
            raise TorchtrackError(f"--steps must be >= 1; got {steps}")
        p_survival = fcfg["p_survival"] if p_survival is None else p_survival
        gen = torch.Generator().manual_seed(seed)
        truth = make_truth(scene, steps)
        rec = simulate(scene, truth, runs, gen)
        filt = build_filter(fcfg, scene, p_survival)
        variants, per_step, mean = {}, {}, {}
        for variant in VARIANTS + EXTRA_VARIANTS:
            variants[variant] = run_variant(variant, filt, rec, cfg, progress)
            o = ospa_per_step(truth, variants[variant], cfg["ospa"]["c"], cfg["ospa"]["p"])
            per_step[variant] = o.mean(1)
            mean[variant] = float(o.mean())
    return PedestrianReport(truth, variants, per_step, mean, cfg, runs, steps, p_survival, seed)


def format_report(r: PedestrianReport) -> str:
    """The OSPA table that ``torchtrack scenario pedestrian`` prints."""
    mean, ospa_cfg = r.mean_ospa, r.config["ospa"]
    rows = [[v, mean[v], PAPER_OSPA.get(v, "-")] for v in VARIANTS + EXTRA_VARIANTS]
    ordered = mean["joint"] <= mean["inflated"] < mean["naive"]
    return "\n".join([
        f"pedestrian scenario: {r.runs} runs x {r.steps} steps, p_S = {r.p_survival}, OSPA c = "
        f"{ospa_cfg['c']} m, p = {ospa_cfg['p']}",
        format_table(["filter", "mean OSPA", "paper"], rows),
        f"paper's ordering joint <= inflated < naive: {'reproduced' if ordered else 'NOT reproduced'}"
        f" (joint <= inflated_kf: {mean['joint'] <= mean['inflated_kf']})"])


def report_json(r: PedestrianReport) -> dict:
    """The numbers of ``--json``."""
    return {"mean_ospa": {v: r.mean_ospa[v] for v in VARIANTS},
            "ospa_per_step": {v: r.ospa_per_step[v] for v in VARIANTS}, "runs": r.runs,
            "steps": r.steps, "p_survival": r.p_survival, "paper_mean_ospa": PAPER_OSPA,
            "seed": r.seed, "extra_mean_ospa": {v: r.mean_ospa[v] for v in EXTRA_VARIANTS},
            "extra_ospa_per_step": {v: r.ospa_per_step[v] for v in EXTRA_VARIANTS}}
