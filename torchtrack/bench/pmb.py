"""``torchtrack bench pmb``: TOMB/P scans per second, 100 tracks and 150 measurements per scan (2-D CV).

100 targets move by a constant-velocity model; each scan holds their detections (p_D = 0.9) topped up
with uniform clutter to exactly 150 measurements. The filter runs a warm-up until the tracks are
confirmed, then the timed scans (predict + update: batched Kalman updates of all track–measurement
pairs, gating, LBP, the TOMB merge and pruning). Reference: the same TOMB/P step written in NumPy
(vectorised over tracks and measurements the same way, NumPy LBP), timed in the same run on the same
scans from the same state.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchtrack.bench._timing import CLOCKS, BenchResult, best_time, format_result, load_average
from torchtrack.bench.lbp import numpy_lbp
from torchtrack.filters.pmb.filter import PMBFilter, PMBState
from torchtrack.models import ConstantVelocity, LinearPosition
from torchtrack.threads import TRACKER_THREADS, torch_threads

HALF = 1000.0   # surveillance region (-1000, 1000)^2 m
SIGMA = 5.0     # measurement noise, m


def make_scans(targets: int, meas: int, scans: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``(scans, meas, 2)`` measurement sets: detections of CV targets topped up with uniform clutter."""
    x = torch.cat([(2 * torch.rand(targets, 2, generator=gen, dtype=torch.float64) - 1) * 0.8 * HALF,
                   torch.randn(targets, 2, generator=gen, dtype=torch.float64) * 10], -1)
    out = []
    for _ in range(scans):
        x = torch.cat([x[:, :2] + x[:, 2:] + torch.randn(targets, 2, generator=gen, dtype=torch.float64) * 0.5,
                       x[:, 2:] + torch.randn(targets, 2, generator=gen, dtype=torch.float64) * 0.5], -1)
        det = x[torch.rand(targets, generator=gen) < 0.9, :2]
        det = det + SIGMA * torch.randn(det.shape, generator=gen, dtype=torch.float64)
        clutter = (2 * torch.rand(max(meas - det.shape[0], 0), 2, generator=gen, dtype=torch.float64) - 1) * HALF
        z = torch.cat([det, clutter])[:meas]
        out.append(z[torch.randperm(z.shape[0], generator=gen)])
    return torch.stack(out), x


def build(targets: int, meas: int, lbp_iterations: int, lbp_tol: float | None) -> PMBFilter:
    clutter = (meas - 0.9 * targets) / (2 * HALF) ** 2
    return PMBFilter(ConstantVelocity(2, q=1.0, learnable=False), LinearPosition(2, sigma=SIGMA, learnable=False),
                     p_survival=0.99, p_detection=0.9, clutter_intensity=clutter, birth_weight=0.01,
                     birth_cov=torch.diag(torch.tensor([HALF**2, HALF**2, 100.0, 100.0])),
                     capacity=int(1.3 * targets) + 16, poisson_capacity=4, gate=0.9999,
                     lbp_iterations=lbp_iterations, lbp_tol=lbp_tol, prune_existence=1e-3, learnable=False)


# ---------------------------------------------------------------------------------------------- NumPy
def _np_pairs(mean, cov, z, H, R):
    PHt = cov @ H.T
    S = H @ PHt + R
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    L = np.linalg.cholesky(S)
    Linv = np.linalg.inv(L)
    nu = z[None, :, :] - (mean @ H.T)[:, None, :]
    white = np.einsum("cab,cmb->cma", Linv, nu)
    d2 = (white**2).sum(-1)
    logdet = 2 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
    log_lik = -0.5 * (d2 + logdet[:, None] + z.shape[-1] * math.log(2 * math.pi))
    W = PHt @ np.swapaxes(Linv, -1, -2)
    K = W @ Linv
    upd_mean = mean[:, None, :] + np.einsum("cab,cmb->cma", K, nu)
    upd_cov = cov - W @ np.swapaxes(W, -1, -2)
    return log_lik, d2, upd_mean, 0.5 * (upd_cov + np.swapaxes(upd_cov, -1, -2))


def numpy_step(st: dict, z: np.ndarray, p: dict) -> dict:
    """One predict + TOMB/P update in NumPy, the same algorithm as :class:`PMBFilter`."""
    F, Q, H, R, pd, ps = p["F"], p["Q"], p["H"], p["R"], p["pd"], p["ps"]
    r, m, P = ps * st["r"], st["m"] @ F.T, F @ st["P"] @ F.T + Q
    plw, pm, pP = st["plw"] + math.log(ps), st["pm"] @ F.T, F @ st["pP"] @ F.T + Q
    keep = np.argsort(-plw)[: len(plw) - 1]
    plw = np.concatenate([plw[keep], [math.log(p["bw"])]])
    pm = np.concatenate([pm[keep], p["bm"][None]])
    pP = np.concatenate([pP[keep], p["bP"][None]])
    ll, d2, um, uP = _np_pairs(m, P, z, H, R)
    valid = st["label"] >= 0
    gated = (d2 < p["gate"]) & valid[:, None]
    with np.errstate(divide="ignore"):
        log_w = np.where(gated, np.log(np.where(valid, r, 1.0))[:, None] + math.log(pd) + ll, -np.inf)
        log_miss = np.log(1 - r * pd)
    pll, _, pum, puP = _np_pairs(pm, pP, z, H, R)
    l_kj = plw[:, None] + math.log(pd) + pll
    mx = l_kj.max(0)
    log_e = mx + np.log(np.exp(l_kj - mx).sum(0))
    log_lam = np.logaddexp(log_e, math.log(p["kappa"]))
    w = np.exp(l_kj - mx)
    w = w / w.sum(0)
    new_m = np.einsum("km,kma->ma", w, pum)
    dn = pum - new_m[None]
    new_P = np.einsum("km,kab->mab", w, puP) + np.einsum("km,kma,kmb->mab", w, dn, dn)
    assoc, miss = numpy_lbp(log_w, log_miss, log_lam, p["iters"], p["tol"])
    psi_col = assoc  # track side; the measurement side for the new targets:
    new = 1.0 - psi_col.sum(0)
    r_miss = r * (1 - pd) / (1 - r * pd)
    a0 = miss * r_miss
    r_post = a0 + assoc.sum(-1)
    den = np.maximum(r_post, 1e-300)
    m_post = (a0[:, None] * m + (assoc[..., None] * um).sum(1)) / den[:, None]
    d0 = m - m_post
    dj = um - m_post[:, None]
    P_post = (a0[:, None, None] * (P + d0[:, :, None] * d0[:, None, :]) + assoc.sum(-1)[:, None, None] * uP
              + np.einsum("nm,nma,nmb->nab", assoc, dj, dj)) / den[:, None, None]
    r_new = np.clip(new, 0, 1) * np.exp(np.minimum(log_e - log_lam, 0))
    r_all = np.concatenate([np.where(valid, r_post, 0.0), r_new])
    keep = np.argsort(-np.where(r_all >= 1e-3, r_all, -1))[: p["cap"]]
    lab = np.concatenate([np.where(valid, st["label"], -1), st["next"] + np.arange(len(z))])
    ok = r_all[keep] >= 1e-3
    return {"r": np.where(ok, r_all[keep], 0.0), "m": np.concatenate([m_post, new_m])[keep],
            "P": np.where(ok[:, None, None], np.concatenate([P_post, new_P])[keep], np.eye(4)),
            "label": np.where(ok, lab[keep], -1), "next": st["next"] + len(z),
            "plw": plw + math.log(1 - pd), "pm": pm, "pP": pP}


def _to_numpy_state(st: PMBState) -> dict:
    return {"r": st.existence.numpy().copy(), "m": st.mean.numpy().copy(), "P": st.cov.numpy().copy(),
            "label": st.label.numpy().copy(), "next": int(st.next_label), "plw": st.poisson_log_weight.numpy().copy(),
            "pm": st.poisson_mean.numpy().copy(), "pP": st.poisson_cov.numpy().copy()}


def measure(targets: int = 100, measurements: int = 150, scans: int = 20, dtype: str = "float64",
            lbp_iterations: int = 30, lbp_tol: float = 1e-6, threads: int = TRACKER_THREADS, repeats: int = 3,
            seed: int = 0) -> BenchResult:
    """Time ``scans`` TOMB/P scans (best of ``repeats``, on ``threads`` torch threads) of our filter and of the
    NumPy step from the same state after a warm-up; ``lbp_tol`` 0: a fixed number of LBP iterations."""
    with torch_threads(threads):
        torch_dtype = getattr(torch, dtype)
        gen = torch.Generator().manual_seed(seed)
        warm = 15
        all_scans, _ = make_scans(targets, measurements, warm + scans, gen)
        tol = lbp_tol if lbp_tol > 0 else None
        filt = build(targets, measurements, lbp_iterations, tol).to(torch_dtype)
        with torch.no_grad():
            state = filt.init_state((), undetected_weight=float(targets), dtype=torch_dtype)
            for t in range(warm):
                state, _ = filt.step(state, all_scans[t].to(torch_dtype))
            start = state
            timed = all_scans[warm:].to(torch_dtype)

            def ours():
                s = start
                for t in range(timed.shape[0]):
                    s, _ = filt.step(s, timed[t])
                return s

            t_ours, c_ours = (best_time(ours, repeats, clock=clock) for clock in CLOCKS)
            final = ours()
        live = int((start.existence > 0.5).sum())
        params = {"F": filt.motion.transition_matrix(1.0).double().numpy(),
                  "Q": filt.motion.process_noise(1.0).double().numpy(), "H": filt.measurement.matrix().double().numpy(),
                  "R": filt.measurement.noise_cov().double().numpy(), "pd": 0.9, "ps": 0.99,
                  "kappa": float(filt.clutter_intensity()), "bw": float(filt.birth_weight()),
                  "bm": filt.birth_mean.double().numpy(), "bP": filt.birth_cov.double().numpy(), "gate": filt.gate_d2,
                  "iters": lbp_iterations, "tol": tol, "cap": filt.capacity}
        np_start = _to_numpy_state(start.__class__(*[t.double() if t.is_floating_point() else t for t in start]))
        timed_np = timed.double().numpy()

        def reference():
            s = np_start
            for t in range(timed_np.shape[0]):
                s = numpy_step(s, timed_np[t], params)
            return s

        t_ref, c_ref = (best_time(reference, repeats, clock=clock) for clock in CLOCKS)
        ref_final = reference()
        agree = abs(float(final.existence.sum()) - float(ref_final["r"].sum()))
        n = timed.shape[0]
        return BenchResult(
            f"TOMB/P predict+update, {targets} targets, {measurements} measurements/scan, "
            f"capacity {filt.capacity}, LBP cap {lbp_iterations} tol {tol}, {dtype}",
            n / t_ours, "numpy (same algorithm)", n / t_ref, "scans",
            {"confirmed_tracks": live, "ms_per_scan": 1e3 * t_ours / n, "numpy_ms_per_scan": 1e3 * t_ref / n,
             "cpu_ms_per_scan": 1e3 * c_ours / n, "numpy_cpu_ms_per_scan": 1e3 * c_ref / n,
             "load_average": load_average(), "expected_count_difference": agree, "threads": torch.get_num_threads()})


def format_report(r: BenchResult, scans: int) -> str:
    """The tracks and the expected-count difference after ``scans`` timed scans, the CPU times and the table."""
    e = r.extra
    return "\n".join([
        f"{e['confirmed_tracks']} confirmed tracks at the start of the timed scans; expected-count difference "
        f"torchtrack vs numpy after {scans} scans: {e['expected_count_difference']:.2e}",
        f"CPU time per scan: torchtrack {e['cpu_ms_per_scan']:.2f} ms, numpy {e['numpy_cpu_ms_per_scan']:.2f} ms "
        f"({e['threads']} threads)",
        format_result(r)])
