"""The δ-GLMB filter with the joint prediction–update and Gibbs truncation of B.-N. Vo, B.-T. Vo and H. G. Hoang,
"An efficient implementation of the generalized labeled multi-Bernoulli filter", IEEE TSP 65(8), 2017, with
Gaussian single-target densities.

Representation (:class:`GLMBState`): a **track table** — one Gaussian ``N(x; m_t, P_t)`` per (label, association
history), ``t = 0 … T−1``, with its label ``ℓ = (birth frame, birth index)`` — and **hypotheses** ``I_h`` (sets of
table rows, at most one per label) with weights ``w_h``, grouped: the labels are partitioned into **groups**, each
an independent δ-GLMB with its own hypotheses (weights normalised within the group). The multi-object density is
the product over groups ``g`` of ``Σ_{h ∈ g} w_h δ_{I_h}(L(X_g)) Π_{t ∈ I_h} N(x_t; m_t, P_t)``; with a single
group this is the paper's δ-GLMB. (Equations are numbered (G·) here; the paper's own numbering is not reproduced.)

Why groups: one joint δ-GLMB over a whole WAMI frame (~100 vehicles) multiplies every vehicle's alternatives, and
the hypothesis cap then keeps only the heaviest combinations — the alternative "this track died" (weight ratio
``(1 − p_S) / (p_S (1 − p_D))`` ≈ 0.1 per frame) never makes the cut, and lost tracks coast for ever. Split into
independent groups (as the large-scale GLMB of Beard, Vo & Vo, IEEE TSP 2020), every group keeps its own
alternatives.

One frame (:meth:`GLMBFilter.step`), births ``B`` (rows of existence ``r_B``) given:

| (G1) prediction of every table row and birth row: ``m⁻ = F m``, ``P⁻ = F P Fᵀ + Q``;
| (G2) for each of the ``N = T + B`` predicted rows ``i`` and measurement ``z_j`` (gated: NIS ≤ χ²(gate)):
     ``η_i(0) = 1 − p_S`` (absent; births ``1 − r_B``), ``η_i(1) = p_S (1 − p_D)`` (missed; births
     ``r_B (1 − p_D)``), ``η_i(j) = p_S p_D N(z_j; H m⁻_i, S_i) / κ(z_j)`` (births with ``r_B``)
     — the per-track weights of the joint prediction–update;
| (G3) this frame's groups are the connected components of the label–measurement gating graph; the prior of a
     group is the product of the old groups' hypotheses projected onto it (exact where old groups join; where an
     old group splits, its parts are its marginals, the one approximation, exact when the parts were
     independent). For each hypothesis ``h``, ``c_h ∝ √w_h`` (``chains`` per group) Gibbs chains
     (:mod:`torchtrack.association.gibbs`, the paper's sampler) draw joint choices ``γ`` over the group's
     labels and births;
| (G4) each distinct ``(h, γ)`` (duplicates kept once) is a new hypothesis with
     ``log w_{h,γ} = log w_h + Σ_{i ∈ I_h ∪ B_g} log η_i(γ_i)``, normalised in the log domain within its group;
     hypotheses of a group that end as the same set of new rows are merged (weights added);
| (G5) new table rows are the distinct ``(i, γ_i)`` with ``γ_i ≠ absent``: the predicted density (missed) or
     its Kalman update with ``z_j`` (:func:`torchtrack.gaussian.kalman_update`);
| (G6) per group: pruning (``w < prune_threshold``, the heaviest always kept) and the cap (``max_hypotheses``
     heaviest; hits counted and warned once), renormalisation; unused table rows dropped;
| (G7) estimate, per group: the MAP cardinality ``n* = argmax_n Σ_{|I_h| = n} w_h`` and the heaviest hypothesis of
     that cardinality; the frame's estimate is their union.

Stop-gradient steps: the gating, the grouping, the sampled choices ``γ`` and every selection made from them
(distinct, merge, prune, cap, estimate) are discrete. The means, covariances and log-weights of what is selected
stay differentiable with respect to ``F, Q, H, R, p_S, p_D, κ`` and the birth densities.

Shapes: state size ``n``, measurement size ``m``, ``T`` table rows, ``H`` hypotheses of at most ``L`` rows.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.association.gibbs import ABSENT, FIRST_MEASUREMENT, MISSED, Groups, gating_groups, gibbs_sample
from torchtrack.filters.glmb.gating import gated_candidates
from torchtrack.gaussian import chi2_quantile, innovation_cov, kalman_gain, kalman_update, symmetrize

log = logging.getLogger(__name__)


class GLMBState(NamedTuple):
    """A δ-GLMB density: the track table and the hypotheses over it."""

    mean: Tensor        # (T, n)
    cov: Tensor         # (T, n, n)
    label: Tensor       # (T, 2) long: (birth frame, birth index)
    meas: Tensor        # (T,) long: measurement of the last frame each row took (-1: none)
    hyp: Tensor         # (H, L) long: table rows of each hypothesis, ascending, -1 padding
    log_weight: Tensor  # (H,) log-weights, normalised within each group
    group: Tensor       # (H,) long: the group of each hypothesis (groups are independent GLMBs)


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
                     torch.zeros(1, dtype=dtype, device=device), torch.zeros(1, **long))


def _log(p: float) -> float:
    return math.log(p) if p > 0 else -math.inf


def _first_of_each(hashes: Tensor) -> tuple[Tensor, Tensor]:
    """Distinct values of ``hashes (R,)``, ascending: the first row of each ``(U,)`` and each row's group
    ``(R,)`` (one stable sort)."""
    srt, order = torch.sort(hashes, stable=True)
    new = torch.ones_like(srt, dtype=torch.bool)
    new[1:] = srt[1:] != srt[:-1]
    inverse = torch.empty_like(order)
    inverse[order] = torch.cumsum(new, 0) - 1
    return order[new], inverse


def _hash_coefficients(n: int) -> Tensor:
    """``n`` fixed odd 63-bit integers (the same for every run)."""
    return torch.randint(1, 2**62, (n,), generator=torch.Generator().manual_seed(0x61B), dtype=torch.long) * 2 + 1


_HASH = _hash_coefficients(4096)


def _row_hash(rows: Tensor, lead: Tensor | None = None) -> Tensor:
    """A 64-bit hash of each row of ``rows (R, D)`` (small non-negative integers), preceded by ``lead (R,)`` where
    given: a fixed random linear form with wrap-around (two distinct rows collide with probability about 2⁻⁶⁴)."""
    D = rows.shape[1] + (lead is not None)
    coef = (_HASH if D <= _HASH.shape[0] else _hash_coefficients(D)).to(rows.device)
    # an integer matrix–vector product where the device has one (the CPU), else products and a sum: the same value
    c = coef[D - rows.shape[1]:D]
    h = rows @ c if rows.device.type == "cpu" else (rows * c).sum(1)
    return h if lead is None else lead * coef[0] + h


def _logsumexp_by(log_w: Tensor, group: Tensor, n: int) -> Tensor:
    """``log Σ exp(log_w)`` over the rows of each of ``n`` groups ``(n,)`` (``-inf`` for an empty group)."""
    top = torch.full((n,), -math.inf, dtype=log_w.dtype, device=log_w.device).scatter_reduce(
        0, group, log_w.detach(), "amax")
    top = torch.where(torch.isfinite(top), top, torch.zeros_like(top))
    return torch.log(torch.zeros(n, dtype=log_w.dtype, device=log_w.device)
                     .index_add(0, group, torch.exp(log_w - top[group]))) + top


def _rank_in_group(log_w: Tensor, group: Tensor) -> Tensor:
    """Each row's rank by decreasing weight within its group ``(R,)`` (0: the heaviest)."""
    order = torch.sort(log_w.detach(), descending=True, stable=True).indices
    order = order[torch.sort(group[order], stable=True).indices]
    g = group[order]
    first = torch.ones_like(g, dtype=torch.bool)
    first[1:] = g[1:] != g[:-1]
    start = torch.cummax(torch.where(first, torch.arange(g.shape[0], device=g.device), 0), 0).values
    rank = torch.empty_like(order)
    rank[order] = torch.arange(g.shape[0], device=g.device) - start
    return rank


class GLMBFilter:
    """The joint prediction–update δ-GLMB (module docstring).

    Args:
        F, Q: ``(n, n)`` transition and process noise for one frame. H_pos, R_pos: ``(2, n)``, ``(2, 2)`` the
            position measurement; H_full, R_full: the measurement with the detector's velocity ``[z, v]``
            (None: positions only).
        p_survival, p_detection: ``p_S``, ``p_D``. gate: χ² gate probability.
        chains: Gibbs chains per group and frame (shared among its hypotheses in proportion to ``√w_h``);
            sweeps: samples per chain. prune_threshold: hypotheses lighter are dropped; max_hypotheses: the cap
            per group.
        generator: random stream of the sampler.
    """

    def __init__(self, F: Tensor, Q: Tensor, H_pos: Tensor, R_pos: Tensor, H_full: Tensor | None,
                 R_full: Tensor | None, p_survival: float, p_detection: float, gate: float, chains: int,
                 sweeps: int, prune_threshold: float, max_hypotheses: int, generator: torch.Generator | None = None):
        self.F, self.Q = F, Q
        self.H_pos, self.R_pos, self.H_full, self.R_full = H_pos, R_pos, H_full, R_full
        self.p_survival, self.p_detection = p_survival, p_detection
        self.gate = gate
        self._gate_thresholds: dict[tuple[float, int], float] = {}
        self.chains, self.sweeps = chains, sweeps
        self.log_prune = _log(prune_threshold)
        self.max_hypotheses = max_hypotheses
        self.generator = generator
        self.cap_hits = 0

    def step(self, state: GLMBState, births: Births, z: Tensor, log_clutter: Tensor,
             velocity: Tensor | None = None) -> tuple[GLMBState, StepInfo]:
        """One frame (G1–G7): ``z (M, 2)`` positions, ``velocity (M, 2)`` or None, ``log_clutter (M,)``
        ``log κ(z_j)`` (of ``[z, v]`` where velocities are used)."""
        T = state.mean.shape[0]
        with_velocity = velocity is not None and self.H_full is not None
        H, R = (self.H_full, self.R_full) if with_velocity else (self.H_pos, self.R_pos)
        meas = torch.cat([z, velocity], 1) if with_velocity else z
        M = meas.shape[0]
        device = meas.device
        # (G1) prediction of table and births
        F, Q = self.F, self.Q
        mean = torch.cat([state.mean, births.mean]) @ F.T
        cov = symmetrize(F @ torch.cat([state.cov, births.cov]) @ F.T + Q)
        label = torch.cat([state.label, births.label])
        N = mean.shape[0]
        if N == 0:
            new = empty_state(mean.shape[1], mean.dtype, device)
            return new, self._info(new, M, 1, False)
        # (G2) gated likelihoods and the weights η
        C, S = innovation_cov(cov, H, R)
        gain = kalman_gain(S, C, "GLMB: innovation covariance S")
        cand, vals = gated_candidates(mean @ H.T, S, gain, meas, self._gate_threshold(meas.shape[1]))
        log_ps = torch.full((T,), _log(self.p_survival), dtype=mean.dtype, device=device)
        log_exist = torch.cat([log_ps, births.log_r])
        log_absent = torch.cat([torch.full_like(log_ps, _log(1 - self.p_survival)),
                                torch.log1p(-torch.exp(births.log_r))])
        clutter = log_clutter[cand.clamp_min(0)] if M else vals
        log_eta = torch.cat([log_absent.unsqueeze(1), (log_exist + _log(1 - self.p_detection)).unsqueeze(1),
                             log_exist.unsqueeze(1) + _log(self.p_detection) + vals - clutter], 1)
        # groups: label slots linked by shared gated measurements; the prior over each (G3)
        _, slot_of_row = torch.unique(label[:, 1], return_inverse=True)
        n_slots = int(slot_of_row.max()) + 1 if N else 0
        groups = gating_groups(cand, slot_of_row, n_slots, M)
        n_groups = groups.slots.shape[0]
        prior_hyp, prior_w, prior_group, product_capped = self._regroup(state, groups.group_of_slot[slot_of_row[:T]],
                                                                        n_groups)
        # (G3) Gibbs chains: `chains` per group, shared among its hypotheses in proportion to √w_h
        half = 0.5 * prior_w.detach()
        share = torch.exp(half - _logsumexp_by(half, prior_group, n_groups)[prior_group])
        counts = torch.ceil(share * self.chains).long().clamp_min(1)
        size = (groups.slots < n_slots).sum(1)[prior_group]          # slots per hypothesis's group
        by_size = torch.sort(size, descending=True, stable=True).indices        # chains by decreasing size
        parent = torch.repeat_interleave(by_size, counts[by_size])
        chain_size = torch.repeat_interleave(size[by_size], counts[by_size])
        active = torch.searchsorted(-chain_size, -torch.arange(len(groups.widths), device=device), right=False)
        rows = self._chain_rows(prior_hyp, prior_group, parent, slot_of_row, groups, T, N)
        # measurement indices local to each group: a chain's record of taken measurements is the group's size
        local_cand = torch.where(cand >= 0, groups.local_meas[cand.clamp_min(0)], -1)
        choice = gibbs_sample(log_eta, local_cand, rows, groups.widths, groups.group_meas, self.sweeps,
                              self.generator, active.tolist())
        P = rows.shape[1]
        choice = choice.reshape(parent.shape[0] * self.sweeps, P)
        # (G4) distinct samples and their weights (sample s of chain c is row c · sweeps + s)
        first, _ = _first_of_each(_row_hash(choice, parent.repeat_interleave(self.sweeps)))
        chain = torch.div(first, self.sweeps, rounding_mode="floor")
        choice, parent, rows = choice[first], parent[chain], rows[chain]
        has_row = rows >= 0
        contrib = log_eta[rows.clamp_min(0), choice] if N else torch.zeros(choice.shape, dtype=mean.dtype)
        log_w = prior_w[parent] + torch.where(has_row, contrib, torch.zeros_like(contrib)).sum(1)
        group = prior_group[parent]
        # (G5) new table rows: distinct (row, choice) of the existing
        width = log_eta.shape[1]
        exists = has_row & (choice != ABSENT)
        keys, new_index = torch.unique((rows * width + choice)[exists], return_inverse=True)
        rows_new = torch.full_like(rows, -1)
        rows_new[exists] = new_index
        hyp = _compact(rows_new)
        # hypotheses of a group that are the same set of new rows merge
        first, same = _first_of_each(_row_hash(hyp + 1, group))
        log_w = _logsumexp_by(log_w, same, first.shape[0])
        hyp, group = hyp[first], group[first]
        log_w = log_w - _logsumexp_by(log_w, group, n_groups)[group]
        # (G6) prune, cap (per group)
        rank = _rank_in_group(log_w, group)
        keep = (log_w.detach() >= self.log_prune) | (rank == 0)
        capped = product_capped or bool((keep & (rank >= self.max_hypotheses)).any())
        if capped:
            self._cap_hit()
        keep &= rank < self.max_hypotheses
        hyp, log_w, group = hyp[keep], log_w[keep], group[keep]
        log_w = log_w - _logsumexp_by(log_w, group, n_groups)[group]
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
            at = (hit.nonzero().squeeze(1),)
            table_mean, table_cov = table_mean.index_put(at, upd.mean), table_cov.index_put(at, upd.cov)
        new = GLMBState(table_mean, table_cov, label[row], new_meas, hyp, log_w, group)
        return new, self._info(new, M, n_groups, capped)

    @staticmethod
    def _chain_rows(prior_hyp: Tensor, prior_group: Tensor, parent: Tensor, slot_of_row: Tensor, groups: Groups,
                    T: int, N: int) -> Tensor:
        """The row each chain updates at each step of a sweep ``(C, P)`` (-1: none): its hypothesis's row of the
        slot at that step of its group, and the group's birth rows (in every hypothesis). Memory ``O((Hp + C) P)``:
        every row of a hypothesis lies in its group."""
        P = groups.slots.shape[1]
        held = prior_hyp >= 0
        step = torch.where(held, groups.position[slot_of_row[prior_hyp.clamp_min(0)]], P)
        row_at = torch.full((prior_hyp.shape[0], P + 1), -1, dtype=torch.long, device=prior_hyp.device)
        row_at.scatter_(1, step, prior_hyp)
        birth_slot = slot_of_row[T:]
        birth_at = torch.full((groups.slots.shape[0], P), -1, dtype=torch.long, device=prior_hyp.device)
        birth_at[groups.group_of_slot[birth_slot], groups.position[birth_slot]] = torch.arange(
            T, N, device=prior_hyp.device)
        births = birth_at[prior_group[parent]]
        return torch.where(births >= 0, births, row_at[parent, :P])

    def _gate_threshold(self, dof: int) -> float:
        """χ²(gate) quantile of ``dof`` degrees of freedom (computed once per size)."""
        key = (self.gate, dof)
        if key not in self._gate_thresholds:
            self._gate_thresholds[key] = chi2_quantile(self.gate, dof)
        return self._gate_thresholds[key]

    def _cap_hit(self) -> None:
        self.cap_hits += 1
        if self.cap_hits == 1:   # info, not a warning: the cap is a documented bound the user need not act on
            log.info("GLMB: hypothesis cap hit (more than %d hypotheses of one group above the prune threshold): "
                        "the lightest are dropped (frames with a hit are counted in cap_hits)", self.max_hypotheses)

    def _regroup(self, state: GLMBState, group_of_row: Tensor, n_groups: int) -> tuple[Tensor, Tensor, Tensor, bool]:
        """The prior of each new group (G3): the old groups' hypotheses projected onto the new groups (an old
        group split by the gating is marginalised; exact when its parts were independent) and, where a new group
        joins several old ones, the product of their projections (exact). ``group_of_row (T,)``: the new group
        of each table row. Returns hypotheses ``(Hp, L)``, log-weights normalised per group, their groups and
        whether a product was capped. A new group with no table row (births only) gets the empty hypothesis."""
        device = state.hyp.device
        H = state.hyp.shape[0]
        member = state.hyp >= 0
        entry = state.hyp.clamp_min(0)
        old_of_row = torch.zeros(group_of_row.shape[0], dtype=torch.long, device=device)
        old_of_row[state.hyp[member]] = state.group.unsqueeze(1).expand_as(state.hyp)[member]
        # pairs (old group, new group) linked by a row, and each hypothesis of the old group against each pair
        n_old = int(state.group.max()) + 1 if H else 0
        pair_key = torch.unique(old_of_row * n_groups + group_of_row)
        pair_old, pair_new = pair_key // n_groups, pair_key % n_groups
        n_pairs = torch.bincount(pair_old, minlength=n_old)
        pair_start = torch.cumsum(n_pairs, 0) - n_pairs
        per_h = n_pairs[state.group]
        h_idx = torch.repeat_interleave(torch.arange(H, device=device), per_h)
        offset = torch.arange(h_idx.shape[0], device=device) - torch.repeat_interleave(torch.cumsum(per_h, 0) - per_h,
                                                                                          per_h)
        q = pair_start[state.group[h_idx]] + offset
        rows = state.hyp[h_idx]
        inside = member[h_idx] & (group_of_row[entry[h_idx]] == pair_new[q].unsqueeze(1))
        proj = _compact(torch.where(inside, rows, -1))
        first, same = _first_of_each(_row_hash(proj + 1, q))
        proj_w = _logsumexp_by(state.log_weight[h_idx], same, first.shape[0])
        proj, proj_q = proj[first], q[first]
        proj_new = pair_new[proj_q]
        # new groups of one factor take it as it is; several factors: their product; none: the empty set
        factors = torch.bincount(pair_new, minlength=n_groups)
        single = factors[proj_new] == 1
        prod_h, prod_w, prod_group, capped = _products(proj, proj_w, proj_q, pair_new, factors, self.max_hypotheses)
        hyps, weights, groups = [proj[single], prod_h], [proj_w[single], prod_w], [proj_new[single], prod_group]
        empty = torch.nonzero(factors == 0).squeeze(1)
        hyps.append(torch.empty(empty.shape[0], 0, dtype=torch.long, device=device))
        weights.append(torch.zeros(empty.shape[0], dtype=proj_w.dtype, device=device))
        groups.append(empty)
        width = max(h.shape[1] for h in hyps)
        hyp = torch.cat([torch.nn.functional.pad(h, (0, width - h.shape[1]), value=-1) for h in hyps])
        log_w, group = torch.cat(weights), torch.cat(groups)
        return hyp, log_w - _logsumexp_by(log_w, group, n_groups)[group], group, capped

    @staticmethod
    def _info(state: GLMBState, n_meas: int, n_groups: int, capped: bool) -> StepInfo:
        """Measurement usage, row existence and the estimate (G7, per group) of ``state``."""
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
        rho = torch.zeros(n_groups * (L + 1), dtype=w.dtype, device=w.device).index_add(
            0, state.group * (L + 1) + card, w).reshape(n_groups, L + 1)
        at_map = card == rho.argmax(1)[state.group]
        rank = _rank_in_group(torch.where(at_map, state.log_weight.detach(), -math.inf), state.group)
        best = state.hyp[(rank == 0) & at_map]
        return StepInfo(used.clamp(0.0, 1.0), best[best >= 0], existence, capped)


def _products(proj: Tensor, proj_w: Tensor, proj_q: Tensor, pair_new: Tensor, factors: Tensor, cap: int
              ) -> tuple[Tensor, Tensor, Tensor, bool]:
    """The prior of each new group that joins several old ones (G3): the product of its factors' hypotheses,
    all such groups at once. ``proj (R, L)``, ``proj_w (R,)``, ``proj_q (R,)``: the projected hypotheses, their
    log-weights and (old, new) pairs; ``pair_new (Q,)`` the new group of each pair; ``factors (G,)`` pairs per
    new group. Factors are multiplied in the order of their pairs, each product row ``a`` of the previous
    factors against each row ``b`` of the next as ``a · n + b``; a group's product over ``cap`` rows keeps its
    ``cap`` heaviest (in ``topk``'s order) before the next factor. Returns hypotheses, log-weights, groups (by
    ascending group) and whether a product was capped."""
    device = proj.device
    joined_pair = factors[pair_new] > 1
    pairs = torch.nonzero(joined_pair).squeeze(1)                      # ascending: a group's factors in order
    if pairs.numel() == 0:
        return proj[:0, :0], proj_w[:0], pair_new[:0], False
    pair_group = pair_new[pairs]
    by_group = torch.argsort(pair_group, stable=True)
    pair_at = torch.full((factors.shape[0], int(factors.max())), -1, dtype=torch.long, device=device)
    pair_at[pair_group[by_group], _position_in_group(pair_group[by_group])] = pairs[by_group]
    # each factor's rows, contiguous and in their projection order
    rows = torch.nonzero(joined_pair[proj_q]).squeeze(1)
    rows = rows[torch.argsort(proj_q[rows], stable=True)]
    f_count = torch.bincount(proj_q[rows], minlength=pair_new.shape[0])
    f_start = torch.cumsum(f_count, 0) - f_count
    group = torch.unique(pair_group)
    log_w = torch.zeros(group.shape[0], dtype=proj_w.dtype, device=device)
    hyp = torch.empty(group.shape[0], 0, dtype=torch.long, device=device)
    capped = False
    for i in range(pair_at.shape[1]):
        q = pair_at[group, i]                                          # this factor of each row's group (-1: none)
        n = torch.where(q >= 0, f_count[q.clamp_min(0)], 1)
        rep = torch.repeat_interleave(torch.arange(group.shape[0], device=device), n)
        q = q[rep]
        b = rows[(f_start[q.clamp_min(0)] + torch.arange(rep.shape[0], device=device)
                  - (torch.cumsum(n, 0) - n)[rep]).clamp_max(max(rows.shape[0] - 1, 0))]
        has = q >= 0
        hyp = torch.cat([hyp[rep], torch.where(has.unsqueeze(1), proj[b], -1)], 1)
        log_w = torch.where(has, log_w[rep] + proj_w[b], log_w[rep])
        group = group[rep]
        over = torch.bincount(group)[group] > cap
        if bool(over.any()):
            capped = True
            keep = [torch.nonzero(~over).squeeze(1)]
            for g in torch.unique(group[over]).tolist():               # a group's heaviest, by topk (few groups)
                at = torch.nonzero(group == g).squeeze(1)
                keep.append(at[log_w[at].detach().topk(cap).indices])
            keep = torch.cat(keep)
            keep = keep[torch.argsort(group[keep], stable=True)]
            hyp, log_w, group = hyp[keep], log_w[keep], group[keep]
    return _compact(hyp), log_w, group, capped


def _position_in_group(group: Tensor) -> Tensor:
    """Each row's position among the rows of its group ``(R,)``, the rows of a group being contiguous."""
    first = torch.ones_like(group, dtype=torch.bool)
    first[1:] = group[1:] != group[:-1]
    index = torch.arange(group.shape[0], device=group.device)
    return index - torch.cummax(torch.where(first, index, 0), 0).values


def _compact(rows: Tensor) -> Tensor:
    """Each row of ``rows (R, N)`` (entries ≥ 0, or -1) sorted ascending with its -1's moved to the end,
    trimmed to the longest row's count."""
    big = torch.iinfo(torch.long).max
    srt = torch.where(rows >= 0, rows, big).sort(1).values
    L = int((rows >= 0).sum(1).max()) if rows.numel() else 0
    srt = srt[:, :L]
    return torch.where(srt == big, -1, srt)


__all__ = ["ABSENT", "MISSED", "Births", "GLMBFilter", "GLMBState", "StepInfo", "empty_state"]
