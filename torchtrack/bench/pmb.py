"""``torchtrack bench pmb``: TOMB/P scans per second, 100 tracks and 150 measurements per scan (2-D CV).

100 targets move by a constant-velocity model; each scan holds their detections (p_D = 0.9) topped up
with uniform clutter to exactly 150 measurements. The filter runs a warm-up until the tracks are
confirmed, then the timed scans (predict + update: batched Kalman updates of all track–measurement
pairs, gating, LBP, the TOMB merge and pruning). Reference: the same TOMB/P step written in NumPy
(vectorised over tracks and measurements the same way, NumPy LBP), timed in the same run on the same
scans from the same state.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from torchtrack.bench._timing import best_time, report
from torchtrack.bench.lbp import _loadavg, best_cpu_time, numpy_lbp
from torchtrack.errors import TorchtrackError
from torchtrack.filters.pmb import PMBFilter, PMBState
from torchtrack.models import ConstantVelocity, LinearPosition
from torchtrack.threads import torch_threads

NAME = "pmb"
HELP = "TOMB/P filter scans/s (100 tracks, 150 measurements per scan) against a NumPy implementation"
DESCRIPTION = __doc__

HALF = 1000.0   # surveillance region (-1000, 1000)^2 m
SIGMA = 5.0     # measurement noise, m


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--targets", type=int, default=100, help="targets/tracks (default 100)")
    parser.add_argument("--measurements", type=int, default=150, help="measurements per scan (default 150)")
    parser.add_argument("--scans", type=int, default=20, help="timed scans (default 20)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    parser.add_argument("--lbp-iterations", type=int, default=30, help="LBP iteration cap (default 30)")
    parser.add_argument("--lbp-tol", type=float, default=1e-6,
                        help="LBP tolerance on the miss/new marginals (default 1e-6; 0: fixed iterations)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: on a shared, loaded machine more threads spin and "
                             "wait for each other)")
    parser.add_argument("--repeats", type=int, default=3)


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


def run(args) -> int:
    with torch_threads(args.threads):
        return _run(args)


def _run(args) -> int:
    if args.targets < 1 or args.measurements < 1 or args.scans < 1:
        raise TorchtrackError("--targets, --measurements and --scans must be >= 1")
    dtype = getattr(torch, args.dtype)
    gen = torch.Generator().manual_seed(args.seed)
    warm = 15
    scans, _ = make_scans(args.targets, args.measurements, warm + args.scans, gen)
    tol = args.lbp_tol if args.lbp_tol > 0 else None
    filt = build(args.targets, args.measurements, args.lbp_iterations, tol).to(dtype)
    with torch.no_grad():
        state = filt.init_state((), undetected_weight=float(args.targets), dtype=dtype)
        for t in range(warm):
            state, _ = filt.step(state, scans[t].to(dtype))
        start = state
        timed = scans[warm:].to(dtype)

        def ours():
            s = start
            for t in range(timed.shape[0]):
                s, _ = filt.step(s, timed[t])
            return s

        t_ours = best_time(ours, repeats=args.repeats)
        c_ours = best_cpu_time(ours, repeats=args.repeats)
        final = ours()
    live = int((start.existence > 0.5).sum())
    params = {"F": filt.motion.transition_matrix(1.0).double().numpy(),
              "Q": filt.motion.process_noise(1.0).double().numpy(), "H": filt.measurement.matrix().double().numpy(),
              "R": filt.measurement.noise_cov().double().numpy(), "pd": 0.9, "ps": 0.99,
              "kappa": float(filt.clutter_intensity()), "bw": float(filt.birth_weight()),
              "bm": filt.birth_mean.double().numpy(), "bP": filt.birth_cov.double().numpy(), "gate": filt.gate_d2,
              "iters": args.lbp_iterations, "tol": tol, "cap": filt.capacity}
    np_start = _to_numpy_state(start.__class__(*[t.double() if t.is_floating_point() else t for t in start]))
    timed_np = timed.double().numpy()

    def reference():
        s = np_start
        for t in range(timed_np.shape[0]):
            s = numpy_step(s, timed_np[t], params)
        return s

    t_ref = best_time(reference, repeats=args.repeats)
    c_ref = best_cpu_time(reference, repeats=args.repeats)
    ref_final = reference()
    agree = abs(float(final.existence.sum()) - float(ref_final["r"].sum()))
    print(f"{live} confirmed tracks at the start of the timed scans; expected-count difference "
          f"torchtrack vs numpy after {args.scans} scans: {agree:.2e}")
    n = timed.shape[0]
    print(f"CPU time per scan: torchtrack {1e3 * c_ours / n:.2f} ms, numpy {1e3 * c_ref / n:.2f} ms "
          f"({torch.get_num_threads()} threads, load average {_loadavg()})")
    report(f"TOMB/P predict+update, {args.targets} targets, {args.measurements} measurements/scan, "
           f"capacity {filt.capacity}, LBP cap {args.lbp_iterations} tol {tol}, {args.dtype}",
           n / t_ours, "numpy (same algorithm)", n / t_ref, "scans", args.json,
           extra={"confirmed_tracks": live, "ms_per_scan": 1e3 * t_ours / n, "numpy_ms_per_scan": 1e3 * t_ref / n,
                  "cpu_ms_per_scan": 1e3 * c_ours / n, "numpy_cpu_ms_per_scan": 1e3 * c_ref / n,
                  "load_average": _loadavg(),
                  "expected_count_difference": agree, "threads": torch.get_num_threads()})
    return 0
