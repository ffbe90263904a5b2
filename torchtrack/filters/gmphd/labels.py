"""Label management for the labelled GM-PHD: the label fix (Aguilar et al. 2023, section 2.3) and
per-label estimate extraction (Panta, Clark & Vo 2009).

Both are discrete, stop-gradient selections over the extracted (high-weight) components; they touch
only the integer ``label`` of a :class:`~torchtrack.filters.gmphd.filter.MixtureState`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.filters.gmphd.filter import MixtureState, as_rows, labels_in


def _first_of_label(label: Tensor, order: Tensor) -> Tensor:
    """Given an ordering, stable-sort it by label and mark the first entry of each label group.

    Returns ``(o, first)``: the permutation (indices into ``label``) and a bool mask over it.
    """
    o = order.index_select(0, torch.sort(label.index_select(0, order), stable=True).indices)
    ls = label.index_select(0, o)
    first = torch.ones_like(ls, dtype=torch.bool)
    first[1:] = ls[1:] != ls[:-1]
    return o, first


def value_of_labels(keys: Tensor, values: Tensor, query: Tensor, default: Tensor) -> Tensor:
    """The value ``values[k] (K, …)`` of each label of ``query (Q,)`` found as ``keys[k]`` among the unique labels
    ``keys (K,)``; ``default (Q, …)`` where it is not there."""
    if keys.numel() == 0:
        return default
    order = torch.argsort(keys)
    index = order.index_select(0, torch.searchsorted(keys.index_select(0, order), query).clamp(max=keys.numel() - 1))
    found = (keys.index_select(0, index) == query).view(-1, *(1,) * (values.dim() - 1))
    return torch.where(found, values.index_select(0, index), default)


def label_fix(state: MixtureState, estimate: Tensor, prev_label: Tensor, prev_pos: Tensor,
              next_label: int, pos_dim: int = 2, min_separation: float = 0.0) -> tuple[MixtureState, int]:
    """The label fix of section 2.3: among extracted components sharing a label, the one closest to that
    label's previous estimate ``(x̂_{k−1}, ℓ)`` keeps it (ties and labels without a previous estimate:
    the highest weight); every other one gets a fresh label ``ℓ_α`` from the latent space
    ``next_label, next_label + 1, …``.

    A duplicate within ``min_separation`` of the label's keeper is not relabelled (it is the same target
    seen through a nearby clutter point, not a second target): it keeps the label and is not reported
    (see :func:`best_per_label`).

    Args:
        state: the posterior mixture; ``estimate (J,)`` bool mask of extracted components.
        prev_label (P,), prev_pos (P, pos_dim): the previous frame's estimates.
        next_label: first unused label.

    Returns the relabelled state and the new first unused label.
    """
    idx = as_rows(estimate)
    if idx.numel() < 2:
        return state, next_label
    lab = state.label.index_select(0, idx)
    pos = state.mean.detach().index_select(0, idx)[:, :pos_dim]
    # distance to the label's previous estimate; inf where it has none
    previous = value_of_labels(prev_label, prev_pos.to(pos.dtype), lab, torch.full_like(pos, float("inf")))
    dist = (pos - previous).norm(dim=-1)
    by_weight = torch.argsort(state.log_weight.detach().index_select(0, idx), descending=True)
    by_dist = by_weight.index_select(0, torch.sort(dist.index_select(0, by_weight), stable=True).indices)
    o, first = _first_of_label(lab, by_dist)
    if min_separation > 0:
        position = torch.arange(o.numel(), device=o.device)
        keeper = torch.cummax(torch.where(first, position, torch.zeros_like(o)), 0).values
        apart = (pos[o] - pos[o[keeper]]).norm(dim=-1) > min_separation
        losers = idx[o[~first & apart]]
    else:
        losers = idx[o[~first]]
    n = int(losers.numel())
    if n == 0:
        return state, next_label
    label = state.label.clone()
    label[losers] = torch.arange(next_label, next_label + n, dtype=label.dtype, device=label.device)
    return state._replace(label=label), next_label + n


def best_per_label(state: MixtureState, estimate: Tensor) -> Tensor:
    """Indices of the extracted components to report, one per label (the highest weight), as in the plain
    labelled GM-PHD: duplicates of a label are not reported."""
    idx = as_rows(estimate)
    if idx.numel() < 2:
        return idx
    label = state.label.index_select(0, idx)
    if torch.unique(label).shape[0] == idx.shape[0]:     # labels already unique
        return idx
    by_weight = torch.argsort(state.log_weight.detach().index_select(0, idx), descending=True)
    o, first = _first_of_label(label, by_weight)
    return idx.index_select(0, o[first])


def relabel(state: MixtureState, old: Tensor, new: Tensor) -> MixtureState:
    """Every component labelled ``old[i]`` takes label ``new[i]`` (``old`` unique)."""
    changed = as_rows(old != new)
    if changed.numel() == 0:
        return state
    return state._replace(label=value_of_labels(old.index_select(0, changed), new.index_select(0, changed),
                                                state.label, state.label))


class LostLabels(NamedTuple):
    """Labels reported recently but not at the last frame: ``label (L,)``, last ``pos, vel (L, 2)`` and
    ``age (L,)`` frames since they were last reported."""

    label: Tensor
    pos: Tensor
    vel: Tensor
    age: Tensor


def no_lost_labels(dtype: torch.dtype = torch.float32, device=None) -> LostLabels:
    return LostLabels(torch.empty(0, dtype=torch.long, device=device), torch.empty(0, 2, dtype=dtype, device=device),
                      torch.empty(0, 2, dtype=dtype, device=device), torch.empty(0, dtype=torch.long, device=device))


def label_handover(label: Tensor, pos: Tensor, prev_label: Tensor, prev_pos: Tensor, prev_vel: Tensor,
                   lost: LostLabels, max_distance: float, dt: float = 1.0,
                   tone_of: Callable[[Tensor], Tensor] | None = None, max_tone_gap: float = float("inf")) -> Tensor:
    """Hand a lost label back to the estimate that continues its trajectory (extension of the label fix).

    ``label (E,)``, ``pos (E, 2)``: this frame's estimates; ``prev_label, prev_pos, prev_vel``: last
    frame's. The pool of lost labels is ``lost`` plus last frame's labels not reported now. An estimate
    whose label is neither last frame's nor in ``lost`` is *new*; a new estimate within ``max_distance`` of
    the path a lost label was expected to travel since it was last seen, the segment from ``p`` to
    ``p + v (age + 1) dt`` (a target may have slowed down), takes that label (greedy, closest first).
    With ``tone_of`` (labels → their tones, NaN: unknown), a lost label is not handed to an estimate whose
    label's tone differs from its own by more than ``max_tone_gap``.
    Returns ``(E,)`` the label each estimate should carry.
    """
    if label.numel() == 0:
        return label
    gone = as_rows(~labels_in(prev_label, label))
    ni = as_rows(~labels_in(label, prev_label) & ~labels_in(label, lost.label))
    if ni.numel() == 0 or (lost.label.numel() == 0 and gone.numel() == 0):
        return label
    from torchtrack.association.assignment import greedy

    pool_label = torch.cat([lost.label, prev_label.index_select(0, gone)])
    steps = torch.cat([lost.age + 1, torch.ones_like(gone)]).to(pos.dtype) * dt
    start = torch.cat([lost.pos, prev_pos.index_select(0, gone)]).to(pos.dtype)
    travel = torch.cat([lost.vel, prev_vel.index_select(0, gone)]).to(pos.dtype) * steps.unsqueeze(1)
    free = as_rows(~labels_in(pool_label, label))  # a lost label reported again this frame is not free
    pool_label, start, travel = (x.index_select(0, free) for x in (pool_label, start, travel))
    # distance from each new estimate to the segment [p, p + v·Δt]: robust to a target slowing down
    rel = pos.detach().index_select(0, ni).unsqueeze(1) - start.unsqueeze(0)          # (N, L, 2)
    t = ((rel * travel).sum(-1) / travel.pow(2).sum(-1).clamp_min(1e-9)).clamp(0.0, 1.0)
    dist = (rel - t.unsqueeze(-1) * travel).norm(dim=-1)
    allowed = dist <= max_distance
    if tone_of is not None:
        gap = (tone_of(label[ni]).unsqueeze(1) - tone_of(pool_label).unsqueeze(0)).abs()
        allowed &= ~(gap > max_tone_gap)
    rows, cols = greedy(dist, allowed)
    out = label.clone()
    out[ni[rows]] = pool_label[cols]
    return out


def update_lost(lost: LostLabels, prev_label: Tensor, prev_pos: Tensor, prev_vel: Tensor, label: Tensor,
                max_age: int) -> LostLabels:
    """The lost-label pool after a frame reporting ``label``: last frame's labels that are not reported
    now join it, reported labels leave it, the others age by one; ``age`` counts the frames between the
    last report and the frame just processed, and entries older than ``max_age`` expire."""
    gone = as_rows(~labels_in(prev_label, label))
    keep = as_rows(~labels_in(lost.label, label) & (lost.age + 1 <= max_age))
    return LostLabels(torch.cat([lost.label.index_select(0, keep), prev_label.index_select(0, gone)]),
                      torch.cat([lost.pos.index_select(0, keep), prev_pos.index_select(0, gone).to(lost.pos.dtype)]),
                      torch.cat([lost.vel.index_select(0, keep), prev_vel.index_select(0, gone).to(lost.vel.dtype)]),
                      torch.cat([lost.age.index_select(0, keep) + 1, torch.ones_like(gone)]))


class TentativeLabels(NamedTuple):
    """New labels extracted but not yet reported (the confirmation of :class:`GMPHDTracker`): ``label (T,)``,
    ``count (T,)`` frames it has been extracted, ``misses (T,)`` frames since it was last extracted."""

    label: Tensor
    count: Tensor
    misses: Tensor


def no_tentative_labels(device=None) -> TentativeLabels:
    empty = torch.empty(0, dtype=torch.long, device=device)
    return TentativeLabels(empty, empty, empty)


def confirm_labels(label: Tensor, known: Tensor, tentative: TentativeLabels, alive: Tensor, frames: int,
                   max_misses: int = 0) -> tuple[Tensor, TentativeLabels]:
    """Which of this frame's estimates to report: a label that is ``known (E,)`` (reported before) at once,
    a new one from the ``frames``-th frame it is extracted. A tentative label not extracted now keeps its
    count for up to ``max_misses`` frames while it is still among the mixture's labels ``alive``, so that a
    missed detection delays its confirmation instead of restarting it.

    Returns the bool mask ``(E,)`` of estimates to report and the tentative labels after this frame.
    """
    count = value_of_labels(tentative.label, tentative.count + 1, label, torch.ones_like(label))
    report = known | (count >= frames)
    wait = as_rows(~labels_in(tentative.label, label) & (tentative.misses < max_misses)
                   & labels_in(tentative.label, alive))
    new = as_rows(~report)
    return report, TentativeLabels(torch.cat([label.index_select(0, new), tentative.label.index_select(0, wait)]),
                                   torch.cat([count.index_select(0, new), tentative.count.index_select(0, wait)]),
                                   torch.cat([torch.zeros_like(new), tentative.misses.index_select(0, wait) + 1]))
