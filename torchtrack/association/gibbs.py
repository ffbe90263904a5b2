"""The Gibbs sampler of the joint δ-GLMB prediction–update (Vo, Vo & Hoang, IEEE TSP 65(8) 2017),
many chains at once.

The problem: ``N`` candidate tracks (surviving tracks of one predicted hypothesis and the birth tracks) and
``M`` measurements. Track ``i`` takes one *choice* ``γ_i``::

    0      absent   (died, or was not born)          weight η_i(0) = 1 − p_S       (births: 1 − r_B)
    1      missed   (exists, no measurement)         weight η_i(1) = p_S (1 − p_D)  (births: r_B (1 − p_D))
    2 + k  takes its k-th gated measurement j        weight η_i(j) = p_S p_D g(z_j | ·) / κ(z_j)

and a joint choice ``γ`` is valid when no measurement is taken twice; its probability is
``π(γ) ∝ Π_i η_i(γ_i)`` over valid ``γ`` (the joint prediction–update's association weight). The Gibbs
sampler draws ``γ_i`` from its conditional given the others, ``π(γ_i | γ_{−i}) ∝ η_i(γ_i) · [γ_i takes no
measurement held by another track]``, track after track; a full sweep is one sample. Its stationary
distribution is ``π`` (the paper proves the convergence of this sampler).

Batching: the tracks are grouped by the connected components of the label–measurement gating graph
(:func:`gating_groups`); each chain samples one group (the caller's GLMB keeps one independent GLMB per group),
and all chains of all groups are rows of one ``(C, P)`` tensor: step ``p`` of a sweep updates the ``p``-th track
of every chain at once (chains ordered by decreasing group size, so the chains of groups with fewer than
``p + 1`` tracks, a suffix, are skipped). A sweep is as many steps as the largest group has tracks, not as there
are tracks, chains or hypotheses. The samples are discrete: they carry no gradient (the η's do, in the weights
the caller forms from them).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

ABSENT, MISSED, FIRST_MEASUREMENT = 0, 1, 2
"""Choice codes: column of ``log_eta`` (``2 + k`` is the k-th candidate measurement)."""


class Groups(NamedTuple):
    """The connected components ("groups") of the slot–measurement gating graph: ``slots (K, P)`` the label slots
    of each group in sweep order (padded with ``S``), ``group_of_slot (S,)``, ``position (S,)`` each slot's step
    in its group's sweep, ``widths[p]`` the choice columns step ``p`` of a sweep needs (2 + the most candidates
    of the rows of the slots at that step), ``local_meas (M,)`` each measurement's index among its group's
    measurements (ascending), ``group_meas`` the most measurements of a group."""

    slots: Tensor
    group_of_slot: Tensor
    position: Tensor
    widths: list[int]
    local_meas: Tensor
    group_meas: int


def _rank_within(label: np.ndarray) -> np.ndarray:
    """Each entry's rank among the entries of the same ``label`` (ordered by index) ``(S,)``."""
    size = np.bincount(label)
    order = np.lexsort((np.arange(label.size), label))
    rank = np.empty(label.size, np.int64)
    rank[order] = np.arange(label.size) - np.repeat(np.cumsum(size) - size, size)
    return rank


def gating_groups(cand: Tensor, slot_of_row: Tensor, n_slots: int, n_meas: int) -> Groups:
    """The groups of label slots that share gated measurements (directly or through others). ``cand (N, K)``:
    gated measurement indices per row, ``-1`` padding (a row's candidates first); ``slot_of_row (N,)``: the
    label slot of each row (a slot's rows are alternatives: a hypothesis holds at most one of them).

    The components are found on the sparse graph of the gated pairs (``O(S + M + pairs)``, no dense
    slot × measurement matrix), on the host."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    S = n_slots
    c = cand.cpu().numpy()
    slot = slot_of_row.cpu().numpy()
    i, k = np.nonzero(c >= 0)
    graph = coo_matrix((np.ones(i.size), (slot[i], S + c[i, k])), shape=(S + n_meas, S + n_meas))
    _, comp_all = connected_components(graph, directed=False)
    _, comp = np.unique(comp_all[:S], return_inverse=True)
    size = np.bincount(comp)
    position = _rank_within(comp)
    P = int(size.max(initial=0))
    slots = np.full((size.size, P), S, np.int64)
    slots[comp, position] = np.arange(S)
    n_cand = np.zeros(S, np.int64)
    np.maximum.at(n_cand, slot, (c >= 0).sum(1) if c.size else np.zeros(slot.size, np.int64))
    widths = np.zeros(P, np.int64)
    np.maximum.at(widths, position, n_cand)
    local = _rank_within(comp_all[S:])
    device = cand.device
    return Groups(torch.from_numpy(slots).to(device), torch.from_numpy(comp).to(device),
                  torch.from_numpy(position).to(device), [FIRST_MEASUREMENT + int(w) for w in widths],
                  torch.from_numpy(local).to(device), int(local.max(initial=-1)) + 1)


def gibbs_sample(log_eta: Tensor, cand: Tensor, rows: Tensor, widths: list[int], n_meas: int, sweeps: int,
                 generator: torch.Generator | None = None, active: list[int] | None = None) -> Tensor:
    """Run ``C`` Gibbs chains for ``sweeps`` sweeps; returns each chain's choices after each sweep ``(C, sweeps, P)``.

    Args:
        log_eta: ``(N, K + 2)`` log weights of the choices of each row (module docstring); ``-inf`` for padding.
        cand: ``(N, K)`` measurement index of each candidate, ``-1`` padding.
        rows: ``(C, P)`` the row chain ``c`` updates at step ``p`` of a sweep (its group's ``p``-th label slot, the
            row its hypothesis holds for it), ``-1``: none (held absent).
        widths: choice columns of each step (:class:`Groups`).
        n_meas: ``M``. sweeps: samples per chain. generator: the random stream (same seed, same samples).
        active: chains with a slot at each step, a prefix (chains ordered by decreasing group size); None: all.

    Chains start with every slot absent (always valid). Each conditional is drawn by inverting its cumulative
    distribution with one uniform per chain.
    """
    N, width = log_eta.shape
    C, P = rows.shape
    device = log_eta.device
    eta = log_eta.detach()
    prob = torch.zeros(N + 1, width, dtype=eta.dtype, device=device)       # row N: "no row", absent only
    if N:
        prob[:N] = torch.exp(eta - eta.max(1, keepdim=True).values)
    prob[N, ABSENT] = 1.0
    meas_of = torch.full((N + 1, width), n_meas, dtype=torch.long, device=device)
    meas_of[:N, FIRST_MEASUREMENT:] = torch.where(cand >= 0, cand, n_meas)   # n_meas: "no measurement"
    rows = torch.where(rows >= 0, rows, N)
    choice = torch.zeros(C, P, dtype=torch.long, device=device)
    taken = torch.zeros(C, n_meas + 1, dtype=torch.bool, device=device)
    out = torch.empty(C, sweeps, P, dtype=torch.long, device=device)
    # each step's rows are the same in every sweep: their weights and measurements are read once
    steps = []
    for p, w in enumerate(widths):
        r = rows[:C if active is None else active[p], p]
        steps.append((prob[:, :w].index_select(0, r), meas_of[:, :w].index_select(0, r)))
    # chains of one-slot groups (a suffix of step 0's): nothing else takes a measurement, their conditional is
    # their row's weights in every sweep
    shared = 0 if P == 0 else steps[0][0].shape[0] if P == 1 else steps[1][0].shape[0]
    solo_cum = steps[0][0][shared:].cumsum(-1) if P else prob[:0]
    for s in range(sweeps):
        for p, (pr, mo) in enumerate(steps):
            a = mo.shape[0]                                      # pr, mo: (a, w)
            u = torch.rand(a, 1, generator=generator, dtype=pr.dtype, device=device)
            b = shared if p == 0 else a                          # chains whose slots compete for measurements
            tk = taken[:b]
            tk.scatter_(1, mo[:b].gather(1, choice[:b, p:p + 1]), False)          # release what the slot holds
            cum = pr[:b].masked_fill(tk.gather(1, mo[:b]), 0.0).cumsum(-1)
            # u < total: an option of probability 0 (cum equal to its predecessor's) is never chosen
            new = torch.searchsorted(cum, u[:b] * cum[:, -1:])   # the options with cum < u
            choice[:b, p:p + 1] = new
            tk.scatter_(1, mo[:b].gather(1, new), True)
            tk[:, n_meas] = False
            if b < a:
                choice[b:a, 0:1] = torch.searchsorted(solo_cum, u[b:] * solo_cum[:, -1:])
        out[:, s] = choice
    return out
