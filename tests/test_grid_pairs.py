"""Grid candidate pairs hold every pair within the radius (checked against all pairs, float64)."""

from __future__ import annotations

import torch

from torchtrack.association.grid import disc_candidates


def _as_set(ii: torch.Tensor, jj: torch.Tensor) -> set[tuple[int, int]]:
    return set(zip(ii.tolist(), jj.tolist()))


def test_disc_candidates_hold_every_pair_within_each_radius_once():
    g = torch.Generator().manual_seed(2)
    a = torch.rand(300, 2, generator=g, dtype=torch.float64) * 500
    b = torch.rand(400, 2, generator=g, dtype=torch.float64) * 500 - 20
    radius = 2.0 + 20.0 * torch.rand(300, generator=g, dtype=torch.float64)
    radius[:3] = torch.tensor([60.0, 300.0, 900.0], dtype=torch.float64)   # wide reaches, past the grid's edges
    ii, jj = disc_candidates(a, radius, b)
    near = _as_set(*(torch.cdist(a, b) <= radius.unsqueeze(1)).nonzero().unbind(1))
    found = _as_set(ii, jj)
    assert near <= found and len(found) == ii.numel()              # a superset, each pair once
    assert ii.numel() < 0.2 * a.shape[0] * b.shape[0]              # far from every pair
    empty = disc_candidates(a[:0], radius[:0], b)
    assert empty[0].numel() == 0 and empty[1].numel() == 0

