"""The δ-GLMB filter with the joint prediction–update and Gibbs truncation of B.-N. Vo, B.-T. Vo and H. G. Hoang,
"An efficient implementation of the generalized labeled multi-Bernoulli filter", IEEE TSP 65(8), 2017, with
Gaussian single-target densities.

Representation (:class:`GLMBState`): a **track table** — one Gaussian ``N(x; m_t, P_t)`` per (label, association
history), ``t = 0 … T−1``, with its label ``ℓ = (birth frame, birth index)`` — and ``H`` **hypotheses**, each a
set ``I_h`` of table rows with weight ``w_h`` (``Σ w_h = 1``, kept as ``log w_h``). The multi-object density is
``π(X) = Δ(X) Σ_h w_h δ_{I_h}(L(X)) Π_{t ∈ I_h} N(x_t; m_t, P_t)`` (the δ-GLMB; equations below are numbered
(G·) here and named after the paper's sections).

One frame (:meth:`GLMBFilter.step`), births ``B`` (rows of existence ``r_B``) given:

(G1) prediction of every table row and birth row: ``m⁻ = F m``, ``P⁻ = F P Fᵀ + Q`` (section III-A);
(G2) for each of the ``N = T + B`` predicted rows ``i`` and measurement ``z_j`` (gated: NIS ≤ χ²(gate)):
     ``η_i(0) = 1 − p_S`` (absent; births ``1 − r_B``), ``η_i(1) = p_S (1 − p_D)`` (missed; births
     ``r_B (1 − p_D)``), ``η_i(j) = p_S p_D N(z_j; H m⁻_i, S_i) / κ(z_j)`` (births with ``r_B``)
     — the joint prediction–update's per-track weights (section III-B);
(G3) for each hypothesis ``h``, ``c_h ∝ √w_h`` Gibbs chains (:mod:`torchtrack.association.gibbs`, section IV)
     draw joint choices ``γ`` over the rows of ``I_h`` and the births (rows outside ``I_h`` stay absent);
(G4) each distinct ``(h, γ)`` (duplicates kept once) is a new hypothesis with
     ``log w_{h,γ} = log w_h + Σ_{i ∈ I_h ∪ B} log η_i(γ_i)``, normalised in the log domain; hypotheses
     that end as the same set of new rows are merged (weights added);
(G5) new table rows are the distinct ``(i, γ_i)`` with ``γ_i ≠ absent``: the predicted density (missed) or
     its Kalman update with ``z_j`` (:func:`torchtrack.gaussian.kalman_update`);
(G6) pruning (``w < prune_threshold``) and the cap (``max_hypotheses`` heaviest kept; counted and warned
     once), renormalisation, unused table rows dropped;
(G7) estimate: the MAP cardinality ``n* = argmax_n Σ_{|I_h| = n} w_h`` and the heaviest hypothesis of that
     cardinality.

Stop-gradient steps: the gating, the sampled choices ``γ`` and every selection made from them (distinct,
merge, prune, cap, estimate) are discrete. The means, covariances and log-weights of what is selected stay
differentiable with respect to ``F, Q, H, R, p_S, p_D, κ`` and the birth densities.

Shapes: state size ``n``, measurement size ``m``, ``T`` table rows, ``H`` hypotheses of at most ``L`` rows.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.association.gibbs import ABSENT, FIRST_MEASUREMENT, MISSED, gating_groups, gibbs_sample
from torchtrack.gaussian import (
    chi2_quantile,
    innovation_cov,
    innovations_likelihood,
    kalman_gain,
    kalman_update,
    symmetrize,
)

log = logging.getLogger(__name__)


class GLMBState(NamedTuple):
    """A δ-GLMB density: the track table and the hypotheses over it."""

    mean: Tensor        # (T, n)
    cov: Tensor         # (T, n, n)
    label: Tensor       # (T, 2) long: (birth frame, birth index)
    meas: Tensor        # (T,) long: measurement of the last frame each row took (-1: none)
    hyp: Tensor         # (H, L) long: table rows of each hypothesis, ascending, -1 padding
    log_weight: Tensor  # (H,) normalised log-weights


class Births(NamedTuple):
    """Birth rows joining the next frame (before prediction): ``mean (B, n)``, ``cov (B, n, n)``,
    ``log_r (B,)`` log existence probabilities, ``label (B, 2)``."""

    mean: Tensor
    cov: Tensor
    log_r: Tensor
    label: Tensor


class StepInfo(NamedTuple):
    """What a frame's update reports besides the new density."""

    used: Tensor         # (M,) probability that each measurement was assigned to a track, Σ_h w_h [z_j ∈ h]
    estimate: Tensor     # (E,) table rows of the estimate (G7)
    existence: Tensor    # (T,) Σ_h w_h [row t ∈ I_h] of each table row
    capped: bool         # the hypothesis cap was hit this frame


def empty_state(state_dim: int, dtype: torch.dtype = torch.float64, device=None) -> GLMBState:
    """No track: one hypothesis, the empty set, with weight 1."""
    long = {"dtype": torch.long, "device": device}
    return GLMBState(torch.empty(0, state_dim, dtype=dtype, device=device),
                     torch.empty(0, state_dim, state_dim, dtype=dtype, device=device),
                     torch.empty(0, 2, **long), torch.empty(0, **long), torch.empty(1, 0, **long),
                     torch.zeros(1, dtype=dtype, device=device))


def _log(p: float) -> float:
    return math.log(p) if p > 0 else -math.inf


def _first_of_each(hashes: Tensor) -> tuple[Tensor, Tensor]:
    """Distinct values of ``hashes (R,)``: the first row of each ``(U,)`` and each row's group ``(R,)``."""
    uniq, inverse = torch.unique(hashes, return_inverse=True)
    rows = torch.arange(hashes.shape[0], device=hashes.device)
    first = torch.full((uniq.shape[0],), hashes.shape[0], dtype=torch.long, device=hashes.device)
    return first.scatter_reduce(0, inverse, rows, "amin"), inverse


def _row_hash(rows: Tensor) -> Tensor:
    """A 64-bit hash of each row of ``rows (R, D)`` (small non-negative integers): a fixed random linear form
    with wrap-around (two distinct rows collide with probability about 2⁻⁶⁴)."""
    g = torch.Generator().manual_seed(0x61B)
    coef = torch.randint(1, 2**62, (rows.shape[1],), generator=g, dtype=torch.long).to(rows.device) * 2 + 1
    return (rows * coef).sum(1)


def _logsumexp_by(log_w: Tensor, group: Tensor, n: int) -> Tensor:
    """``log Σ exp(log_w)`` over the rows of each of ``n`` groups."""
    top = log_w.max().detach()
    return torch.log(torch.zeros(n, dtype=log_w.dtype, device=log_w.device)
                     .index_add(0, group, torch.exp(log_w - top))) + top


class GLMBFilter:
    """The joint prediction–update δ-GLMB (module docstring).

    Args:
        F, Q: ``(n, n)`` transition and process noise for one frame. H_pos, R_pos: ``(2, n)``, ``(2, 2)`` the
            position measurement; H_full, R_full: the measurement with the detector's velocity ``[z, v]``
            (None: positions only).
        p_survival, p_detection: ``p_S``, ``p_D``. gate: χ² gate probability.
        chains: Gibbs chains per frame (shared among hypotheses in proportion to ``√w_h``); sweeps: samples
            per chain. prune_threshold: hypotheses lighter are dropped; max_hypotheses: the cap.
        generator: random stream of the sampler.
    """

    def __init__(self, F: Tensor, Q: Tensor, H_pos: Tensor, R_pos: Tensor, H_full: Tensor | None,
                 R_full: Tensor | None, p_survival: float, p_detection: float, gate: float, chains: int,
                 sweeps: int, prune_threshold: float, max_hypotheses: int, generator: torch.Generator | None = None):
        self.F, self.Q = F, Q
        self.H_pos, self.R_pos, self.H_full, self.R_full = H_pos, R_pos, H_full, R_full
        self.p_survival, self.p_detection = p_survival, p_detection
        self.gate = gate
        self.chains, self.sweeps = chains, sweeps
        self.log_prune = _log(prune_threshold)
        self.max_hypotheses = max_hypotheses
        self.generator = generator
        self.cap_hits = 0

    def step(self, state: GLMBState, births: Births, z: Tensor, log_clutter: Tensor,
             velocity: Tensor | None = None) -> tuple[GLMBState, StepInfo]:
        """One frame (G1–G7): ``z (M, 2)`` positions, ``velocity (M, 2)`` or None, ``log_clutter (M,)``
        ``log κ(z_j)`` (of ``[z, v]`` where velocities are used)."""
        T, B = state.mean.shape[0], births.mean.shape[0]
        with_velocity = velocity is not None and self.H_full is not None
        H, R = (self.H_full, self.R_full) if with_velocity else (self.H_pos, self.R_pos)
        meas = torch.cat([z, velocity], 1) if with_velocity else z
        M = meas.shape[0]
        # (G1) prediction of table and births
        F, Q = self.F, self.Q
        mean = torch.cat([state.mean, births.mean]) @ F.T
        cov = symmetrize(F @ torch.cat([state.cov, births.cov]) @ F.T + Q)
        label = torch.cat([state.label, births.label])
        N = T + B
        # (G2) gated likelihoods and the weights η
        C, S = innovation_cov(cov, H, R)
        gain = kalman_gain(S, C, "GLMB: innovation covariance S")
        nu = meas.unsqueeze(0) - (mean @ H.T).unsqueeze(1)                     # (N, M, m)
        nis, loglik = innovations_likelihood(gain, nu)
        gated = nis.detach() <= chi2_quantile(self.gate, meas.shape[1])
        K = int(gated.sum(1).max()) if N and M else 0
        vals, cand = torch.where(gated, loglik, torch.full_like(loglik, -math.inf)).topk(K, dim=1)
        cand = torch.where(torch.isfinite(vals.detach()), cand, torch.full_like(cand, -1))
        log_ps = torch.full((T,), _log(self.p_survival), dtype=mean.dtype, device=mean.device)
        log_exist = torch.cat([log_ps, births.log_r])
        log_absent = torch.cat([torch.full_like(log_ps, _log(1 - self.p_survival)),
                                torch.log1p(-torch.exp(births.log_r))])
        clutter = log_clutter[cand.clamp_min(0)] if M else vals
        log_eta = torch.cat([log_absent.unsqueeze(1), (log_exist + _log(1 - self.p_detection)).unsqueeze(1),
                             log_exist.unsqueeze(1) + _log(self.p_detection) + vals - clutter], 1)
        # (G3) Gibbs chains, √w_h of them per hypothesis, over label slots (a hypothesis holds at most one row
        # per label; births are slots of their own)
        Hn = state.hyp.shape[0]
        slots, slot_of_row = torch.unique(label[:, 1], return_inverse=True)
        n_slots = slots.shape[0]
        share = torch.exp(0.5 * state.log_weight.detach())
        counts = torch.ceil(share / share.sum() * self.chains).long().clamp_min(1)
        parent = torch.repeat_interleave(torch.arange(Hn, device=mean.device), counts)
        row_of_h = torch.full((Hn, n_slots + 1), -1, dtype=torch.long, device=mean.device)
        held = state.hyp >= 0
        row_of_h.scatter_(1, torch.where(held, slot_of_row[state.hyp.clamp_min(0)], n_slots), state.hyp)
        birth_rows = torch.arange(T, N, device=mean.device)
        row_of_h[:, slot_of_row[T:]] = birth_rows
        row_of_h = row_of_h[:, :n_slots]
        choice = gibbs_sample(log_eta, cand, row_of_h[parent], gating_groups(cand, slot_of_row, n_slots, M), M,
                              self.sweeps, self.generator)
        choice = choice.reshape(parent.shape[0] * self.sweeps, n_slots)
        parent = parent.repeat_interleave(self.sweeps)
        # (G4) distinct samples and their weights
        first, _ = _first_of_each(_row_hash(torch.cat([parent.unsqueeze(1), choice], 1)))
        choice, parent = choice[first], parent[first]
        row = row_of_h[parent]                                                  # (U, S)
        has_row = row >= 0
        contrib = log_eta[row.clamp_min(0), choice]
        log_w = state.log_weight[parent] + torch.where(has_row, contrib, torch.zeros_like(contrib)).sum(1)
        # (G5) new table rows: distinct (row, choice) with the row present
        width = log_eta.shape[1]
        exists = has_row & (choice != ABSENT)
        key = torch.where(exists, row * width + choice, -1)
        keys, new_index = torch.unique(key[exists], return_inverse=True)
        rows_new = torch.full_like(key, -1)
        rows_new[exists] = new_index
        hyp = _compact(rows_new)
        # merge hypotheses that are the same set of new rows
        first, group = _first_of_each(_row_hash(hyp + 1))
        log_w = _logsumexp_by(log_w, group, first.shape[0])
        hyp = hyp[first]
        log_w = log_w - torch.logsumexp(log_w, 0)
        # (G6) prune, cap
        keep = log_w.detach() >= self.log_prune
        keep[log_w.detach().argmax()] = True
        capped = int(keep.sum()) > self.max_hypotheses
        if capped:
            self.cap_hits += 1
            if self.cap_hits == 1:
                log.warning("GLMB: hypothesis cap hit (%d hypotheses above the prune threshold, cap %d): the "
                            "lightest are dropped (counted in cap_hits)", int(keep.sum()), self.max_hypotheses)
            keep = torch.zeros_like(keep)
            keep[log_w.detach().topk(self.max_hypotheses).indices] = True
        hyp, log_w = hyp[keep], log_w[keep]
        log_w = log_w - torch.logsumexp(log_w, 0)
        used_rows, remap = torch.unique(hyp[hyp >= 0], return_inverse=True)
        hyp_final = torch.full_like(hyp, -1)
        hyp_final[hyp >= 0] = remap
        hyp = _compact(hyp_final)
        keys = keys[used_rows]
        row, c = keys // width, keys % width
        table_mean, table_cov = mean[row], cov[row]
        hit = c >= FIRST_MEASUREMENT
        j = cand[row[hit], c[hit] - FIRST_MEASUREMENT]
        new_meas = torch.full_like(row, -1)
        new_meas[hit] = j
        if bool(hit.any()):
            upd = kalman_update(mean[row[hit]], cov[row[hit]], meas[j], H, R, check=False)
            table_mean = table_mean.index_put((hit.nonzero().squeeze(1),), upd.mean)
            table_cov = table_cov.index_put((hit.nonzero().squeeze(1),), upd.cov)
        new = GLMBState(table_mean, table_cov, label[row], new_meas, hyp, log_w)
        return new, self._info(new, M, capped)

    @staticmethod
    def _info(state: GLMBState, n_meas: int, capped: bool) -> StepInfo:
        """Measurement usage, row existence and the estimate (G7) of ``state``."""
        w = torch.exp(state.log_weight.detach())
        Hn, L = state.hyp.shape
        member = state.hyp >= 0
        rows = state.hyp[member]
        wh = w.unsqueeze(1).expand(Hn, L)[member]
        T = state.mean.shape[0]
        existence = torch.zeros(T, dtype=w.dtype, device=w.device).index_add(0, rows, wh)
        meas = state.meas[rows]
        used = torch.zeros(n_meas + 1, dtype=w.dtype, device=w.device).index_add(
            0, torch.where(meas >= 0, meas, n_meas), wh)[:n_meas]
        card = member.sum(1)
        rho = torch.zeros(L + 1, dtype=w.dtype, device=w.device).index_add(0, card, w)
        best = torch.where(card == rho.argmax(), state.log_weight.detach(), -math.inf).argmax()
        estimate = state.hyp[best][state.hyp[best] >= 0]
        return StepInfo(used.clamp(0.0, 1.0), estimate, existence, capped)


def _compact(rows: Tensor) -> Tensor:
    """Each row of ``rows (R, N)`` (entries ≥ 0, or -1) sorted ascending with its -1's moved to the end,
    trimmed to the longest row's count."""
    big = torch.iinfo(torch.long).max
    srt = torch.where(rows >= 0, rows, big).sort(1).values
    L = int((rows >= 0).sum(1).max()) if rows.numel() else 0
    srt = srt[:, :L]
    return torch.where(srt == big, -1, srt)


__all__ = ["ABSENT", "MISSED", "Births", "GLMBFilter", "GLMBState", "StepInfo", "empty_state"]
