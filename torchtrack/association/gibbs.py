"""The Gibbs sampler of the joint δ-GLMB prediction–update (Vo, Vo & Hoang, IEEE TSP 65(8) 2017, section IV),
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
distribution is ``π`` (the paper's Proposition on the sampler's convergence).

Batching: every chain is a row of one ``(C, N)`` tensor, and tracks whose gates share no measurement are
conditionally independent, so one step updates one track of **every** group of the gating graph (its
connected components, :func:`gating_groups`) in every chain at once — a sweep is as many steps as the largest
group has tracks, not as there are tracks. The samples are discrete: they carry no gradient (the η's do, in
the weights the caller forms from them).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

ABSENT, MISSED, FIRST_MEASUREMENT = 0, 1, 2
"""Choice codes: column of ``log_eta`` (``2 + k`` is the k-th candidate measurement)."""


class SweepOrder(NamedTuple):
    """The steps of one sweep: ``slots[p]`` the label slots updated together at step ``p`` (one per group, at most),
    ``widths[p]`` the number of choice columns they need (2 + the most candidates of their rows)."""

    slots: list[Tensor]
    widths: list[int]


def gating_groups(cand: Tensor, slot_of_row: Tensor, n_slots: int, n_meas: int) -> SweepOrder:
    """The sweep order over the connected components ("groups") of the slot–measurement gating graph: step
    ``p`` updates the ``p``-th slot of every group that has one. ``cand (N, K)``: gated measurement indices per
    row, ``-1`` padding (a row's candidates first); ``slot_of_row (N,)``: the label slot of each row (a slot's
    rows are alternatives: a hypothesis holds at most one of them)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    S = n_slots
    c = cand.cpu().numpy()
    slot = slot_of_row.cpu().numpy()
    i, k = np.nonzero(c >= 0)
    graph = coo_matrix((np.ones(i.size), (slot[i], S + c[i, k])), shape=(S + n_meas, S + n_meas))
    _, comp = connected_components(graph, directed=False)
    comp = comp[:S]
    size = np.bincount(comp)
    # groups by decreasing size (step p then touches a prefix of them), slots of a group by index
    order = np.lexsort((np.arange(S), comp, -size[comp]))
    sorted_comp = comp[order]
    starts = np.flatnonzero(np.r_[True, sorted_comp[1:] != sorted_comp[:-1]]) if S else np.zeros(0, np.int64)
    sizes = np.diff(np.r_[starts, S])
    position = np.empty(S, np.int64)
    position[order] = np.arange(S) - np.repeat(starts, sizes)
    n_cand = np.zeros(S, np.int64)
    np.maximum.at(n_cand, slot, (c >= 0).sum(1) if c.size else np.zeros(slot.size, np.int64))
    by_position = np.argsort(position, kind="stable")
    bounds = np.searchsorted(position[by_position], np.arange(int(sizes.max(initial=0)) + 1))
    slots = [by_position[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
    return SweepOrder([torch.from_numpy(m).to(cand.device) for m in slots],
                      [FIRST_MEASUREMENT + int(n_cand[m].max(initial=0)) for m in slots])


def gibbs_sample(log_eta: Tensor, cand: Tensor, row_of: Tensor, order: SweepOrder, n_meas: int, sweeps: int,
                 generator: torch.Generator | None = None) -> Tensor:
    """Run ``C`` Gibbs chains for ``sweeps`` sweeps; returns the choice of each label slot after each sweep
    ``(C, sweeps, S)``.

    Args:
        log_eta: ``(N, K + 2)`` log weights of the choices of each row (module docstring); ``-inf`` for padding.
        cand: ``(N, K)`` measurement index of each candidate, ``-1`` padding.
        row_of: ``(C, S)`` the row each chain's hypothesis holds for each label slot, ``-1``: none (the slot is
            held absent).
        order: the sweep order from :func:`gating_groups`.
        n_meas: ``M``. sweeps: samples per chain. generator: the random stream (same seed, same samples).

    Chains start with every slot absent (always valid). Each conditional is drawn by inverting its cumulative
    distribution with one uniform per chain and slot.
    """
    N, width = log_eta.shape
    C = row_of.shape[0]
    device = log_eta.device
    eta = log_eta.detach()
    prob = torch.zeros(N + 1, width, dtype=eta.dtype, device=device)       # row N: "no row", absent only
    prob[:N] = torch.exp(eta - eta.max(1, keepdim=True).values)
    prob[N, ABSENT] = 1.0
    meas_of = torch.full((N + 1, width), n_meas, dtype=torch.long, device=device)
    meas_of[:N, FIRST_MEASUREMENT:] = torch.where(cand >= 0, cand, n_meas)   # n_meas: "no measurement"
    rows = torch.where(row_of >= 0, row_of, N)
    choice = torch.zeros(row_of.shape, dtype=torch.long, device=device)
    taken = torch.zeros(C, n_meas + 1, dtype=torch.bool, device=device)
    out = torch.empty(C, sweeps, row_of.shape[1], dtype=torch.long, device=device)
    for s in range(sweeps):
        for idx, w in zip(*order):                               # (G,) at most one slot per group
            r = rows[:, idx]                                     # (C, G)
            mo = meas_of[r, :w]                                  # (C, G, w)
            G = idx.shape[0]
            taken.scatter_(1, mo.gather(2, choice[:, idx].unsqueeze(2)).view(C, G), False)   # release
            blocked = taken.gather(1, mo.view(C, G * w)).view(C, G, w)
            cum = prob[r, :w].masked_fill(blocked, 0.0).cumsum(-1)
            # u < total: an option of probability 0 (cum equal to its predecessor's) is never chosen
            u = torch.rand(C, G, 1, generator=generator, dtype=cum.dtype, device=device) * cum[..., -1:]
            new = (cum < u).sum(-1)
            choice[:, idx] = new
            taken.scatter_(1, mo.gather(2, new.unsqueeze(2)).view(C, G), True)
            taken[:, n_meas] = False
        out[:, s] = choice
    return out
