"""The batched Gibbs sampler of the joint δ-GLMB update against exact enumeration of its target distribution."""

import itertools
import math

import pytest
import torch

from torchtrack.association.gibbs import gating_groups, gibbs_sample


def _problem(n_tracks: int, n_meas: int, seed: int):
    """Random weights ``η`` (absent, missed, one per measurement) with some pairs outside the gate."""
    g = torch.Generator().manual_seed(seed)
    full = torch.randn(n_tracks, n_meas + 2, generator=g, dtype=torch.float64)
    gated = torch.rand(n_tracks, n_meas, generator=g) < 0.7
    full[:, 2:] = full[:, 2:].masked_fill(~gated, float("-inf"))
    vals, idx = full[:, 2:].topk(n_meas, dim=1)
    cand = torch.where(torch.isfinite(vals), idx, torch.full_like(idx, -1))
    return full, torch.cat([full[:, :2], vals], 1), cand


def _enumerate(full: torch.Tensor, present: torch.Tensor) -> dict[tuple, float]:
    """Exact ``π(γ) ∝ Π η_i(γ_i)`` over valid joint choices, as measurement indices (-2 absent, -1 missed)."""
    n, width = full.shape
    options = [range(-2, width - 2) if present[i] else [-2] for i in range(n)]
    weights = {}
    for gamma in itertools.product(*options):
        taken = [j for j in gamma if j >= 0]
        if len(taken) != len(set(taken)):
            continue
        logw = sum(float(full[i, j + 2]) for i, j in enumerate(gamma) if present[i])
        if logw > -math.inf:
            weights[gamma] = math.exp(logw)
    total = sum(weights.values())
    return {k: v / total for k, v in weights.items()}


def _as_measurements(choice: torch.Tensor, cand: torch.Tensor) -> list[tuple]:
    meas = torch.where(choice >= 2, cand.gather(1, (choice - 2).clamp_min(0).T).T, choice - 2)
    return [tuple(row) for row in meas.tolist()]


@pytest.mark.parametrize("n_tracks,n_meas,seed", [(2, 2, 0), (3, 3, 1), (4, 4, 2), (4, 3, 3)])
def test_empirical_distribution_matches_enumeration(n_tracks, n_meas, seed):
    full, log_eta, cand = _problem(n_tracks, n_meas, seed)
    present = torch.ones(n_tracks, dtype=torch.bool)
    present[-1] = n_tracks < 4 or seed % 2 == 0          # one track outside the hypothesis in some cases
    exact = _enumerate(full, present)
    chains, sweeps, burn = 4000, 6, 2
    rows = torch.where(present, torch.arange(n_tracks), -1).expand(chains, -1)
    out = gibbs_sample(log_eta, cand, rows, [n_meas + 2] * n_tracks, n_meas, sweeps, torch.Generator().manual_seed(7))
    samples = _as_measurements(out[:, burn:].reshape(-1, n_tracks), cand)
    counts: dict[tuple, int] = {}
    for s in samples:
        counts[s] = counts.get(s, 0) + 1
    assert set(counts) <= set(exact)                     # only valid joint choices are ever drawn
    total = len(samples)
    # sweeps of one chain are correlated: the binomial std of 4000 independent chains, times a margin of 5
    for gamma, p in exact.items():
        std = math.sqrt(p * (1 - p) / chains)
        assert abs(counts.get(gamma, 0) / total - p) <= 5 * std + 1e-3, (gamma, p)


def test_groups_are_components_of_the_gating_graph():
    cand = torch.tensor([[0, -1], [0, 1], [2, -1], [-1, -1], [1, -1]])
    groups = gating_groups(cand, torch.arange(5), 5, 3)
    assert sorted(sorted(int(s) for s in g if s < 5) for g in groups.slots) == [[0, 1, 4], [2], [3]]
    assert groups.widths == [3, 4, 3]                                     # 2 + most candidates at each step
    assert groups.group_of_slot[0] == groups.group_of_slot[4] != groups.group_of_slot[2]
    # rows 0 and 2 are alternatives of one label slot: their measurements join one group
    groups = gating_groups(cand, torch.tensor([0, 1, 0, 2, 3]), 4, 3)
    assert sorted(sorted(int(s) for s in g if s < 4) for g in groups.slots) == [[0, 1, 3], [2]]


def test_same_seed_same_samples():
    _, log_eta, cand = _problem(4, 4, 5)
    rows = torch.arange(4).expand(64, -1)
    a = gibbs_sample(log_eta, cand, rows, [6] * 4, 4, 3, torch.Generator().manual_seed(1))
    b = gibbs_sample(log_eta, cand, rows, [6] * 4, 4, 3, torch.Generator().manual_seed(1))
    assert torch.equal(a, b)


def test_one_slot_chains_beside_larger_groups_match_enumeration():
    """Chains of a 3-slot group (rows 0-2, competing for measurements) ahead of chains of one-slot groups (row 3,
    its own measurements): the 3-slot chains follow the enumerated joint posterior, the one-slot chains their
    row's normalised weights — the one-slot suffix is drawn without the bookkeeping of taken measurements."""
    full, log_eta, cand = _problem(4, 4, 5)
    chains, sweeps, burn = 4000, 6, 2
    rows = torch.cat([torch.tensor([[0, 1, 2]]).expand(chains, -1), torch.tensor([[3, -1, -1]]).expand(chains, -1)])
    out = gibbs_sample(log_eta, cand, rows, [6] * 3, 4, sweeps, torch.Generator().manual_seed(11),
                       active=[2 * chains, chains, chains])
    exact_joint = _enumerate(full[:3], torch.ones(3, dtype=torch.bool))
    exact_solo = _enumerate(full[3:], torch.ones(1, dtype=torch.bool))
    for exact, block, track_rows in ((exact_joint, out[:chains, burn:], [0, 1, 2]),
                                     (exact_solo, out[chains:, burn:, :1], [3])):
        samples = _as_measurements(block.reshape(-1, len(track_rows)), cand[track_rows])
        total = len(samples)
        for gamma, p in exact.items():
            std = math.sqrt(p * (1 - p) / chains)
            assert abs(samples.count(gamma) / total - p) <= 5 * std + 1e-3, (gamma, p)
        assert set(samples) <= set(exact)
