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

import numpy as np
import torch
from torch import Tensor

ABSENT, MISSED, FIRST_MEASUREMENT = 0, 1, 2
"""Choice codes: column of ``log_eta`` (``2 + k`` is the k-th candidate measurement)."""


def gating_groups(cand: Tensor, n_meas: int) -> Tensor:
    """The tracks of each connected component of the track–measurement gating graph, as the sweep order
    ``(P, G)``: column ``g`` lists group ``g``'s tracks (padded with ``N``, a dummy track), ``P`` the largest
    group's size. ``cand (N, K)``: gated measurement indices per track, ``-1`` padding."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    N = cand.shape[0]
    c = cand.cpu().numpy()
    i, k = np.nonzero(c >= 0)
    graph = coo_matrix((np.ones(i.size), (i, N + c[i, k])), shape=(N + n_meas, N + n_meas))
    _, comp = connected_components(graph, directed=False)
    comp = comp[:N]
    order = np.argsort(comp, kind="stable")
    sorted_comp = comp[order]
    starts = np.flatnonzero(np.r_[True, sorted_comp[1:] != sorted_comp[:-1]])
    sizes = np.diff(np.r_[starts, N])
    position = np.arange(N) - np.repeat(starts, sizes)
    group = np.repeat(np.arange(starts.size), sizes)
    out = np.full((int(sizes.max(initial=0)), starts.size), N, dtype=np.int64)
    out[position, group] = order
    return torch.from_numpy(out).to(cand.device)


def gibbs_sample(log_eta: Tensor, cand: Tensor, present: Tensor, groups: Tensor, n_meas: int, sweeps: int,
                 generator: torch.Generator | None = None) -> Tensor:
    """Run ``C`` Gibbs chains for ``sweeps`` sweeps; returns the joint choice after each sweep ``(C, sweeps, N)``.

    Args:
        log_eta: ``(N, K + 2)`` log weights of the choices (module docstring); ``-inf`` for padded candidates.
        cand: ``(N, K)`` measurement index of each candidate, ``-1`` padding.
        present: ``(C, N)`` bool, the tracks each chain may use (a surviving track outside the chain's
            hypothesis is held absent).
        groups: ``(P, G)`` sweep order from :func:`gating_groups`.
        n_meas: ``M``. sweeps: samples per chain. generator: the random stream (same seed, same samples).

    Chains start with every track absent (always valid). Each conditional is drawn by Gumbel-max.
    """
    N, width = log_eta.shape
    C = present.shape[0]
    device = log_eta.device
    eta = torch.full((N + 1, width), float("-inf"), dtype=log_eta.dtype, device=device)
    eta[:N] = log_eta.detach()
    eta[N, ABSENT] = 0.0                                       # the dummy track: always absent
    meas_of = torch.full((N + 1, width), n_meas, dtype=torch.long, device=device)
    meas_of[:N, FIRST_MEASUREMENT:] = torch.where(cand >= 0, cand, n_meas)   # n_meas: "no measurement"
    absent_only = torch.zeros(C, N + 1, 1, dtype=torch.bool, device=device)
    absent_only[:, :N, 0] = ~present
    not_absent = torch.arange(width, device=device) != ABSENT
    choice = torch.zeros(C, N + 1, dtype=torch.long, device=device)
    taken = torch.zeros(C, n_meas + 1, dtype=torch.bool, device=device)
    rows = torch.arange(C, device=device).unsqueeze(1)
    out = torch.empty(C, sweeps, N, dtype=torch.long, device=device)
    for s in range(sweeps):
        for idx in groups:                                      # (G,) one track per group
            held = meas_of[idx].gather(1, choice[:, idx].T).T   # (C, G) measurement held now
            taken[rows, held] = False
            taken[:, n_meas] = False
            blocked = taken[:, meas_of[idx]]                    # (C, G, width)
            logits = eta[idx].masked_fill(blocked | (absent_only[:, idx] & not_absent), float("-inf"))
            u = torch.rand(logits.shape, generator=generator, dtype=logits.dtype, device=device)
            new = (logits - torch.log(-torch.log(u.clamp_min(1e-300)))).argmax(-1)
            choice[:, idx] = new
            taken[rows, meas_of[idx].gather(1, new.T).T] = True
            taken[:, n_meas] = False
        out[:, s] = choice[:, :N]
    return out
