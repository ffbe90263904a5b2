"""Assignment solvers against brute-force enumeration of all partial matchings."""

import itertools

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from torchtrack.association.assignment import assign, greedy, hungarian
from torchtrack.association.pairs import max_total_assignment
from torchtrack.errors import TorchtrackError


def _all_matchings(R, C):
    """Every partial injective map rows → cols as a list of (row, col) pairs."""
    for k in range(min(R, C) + 1):
        for rows in itertools.combinations(range(R), k):
            for cols in itertools.permutations(range(C), k):
                yield list(zip(rows, cols))


def _brute(cost, valid, c0=None):
    best_key = None
    for m in _all_matchings(*cost.shape):
        if not all(valid[i, j] for i, j in m):
            continue
        total = sum(cost[i, j] for i, j in m)
        if c0 is None:
            key = (-len(m), total)
        else:
            key = (total + c0 * (cost.shape[0] - len(m)) + c0 * (cost.shape[1] - len(m)),)
        if best_key is None or key < best_key:
            best_key = key
    return best_key


@pytest.mark.parametrize("shape", [(3, 4), (4, 3), (4, 4), (2, 5)])
def test_hungarian_matches_brute_force_with_gates(shape):
    rng = np.random.default_rng(sum(shape))
    for _ in range(20):
        cost = rng.uniform(0, 10, shape)
        valid = rng.uniform(size=shape) < 0.5
        r, k = hungarian(torch.as_tensor(cost), torch.as_tensor(valid))
        assert all(valid[i, j] for i, j in zip(r.tolist(), k.tolist()))
        key = (-len(r), cost[r.numpy(), k.numpy()].sum())
        ref = _brute(cost, valid)
        assert key[0] == ref[0] and key[1] == pytest.approx(ref[1])


def test_hungarian_unassigned_cost_matches_brute_force():
    rng = np.random.default_rng(1)
    for _ in range(20):
        cost = rng.uniform(0, 10, (3, 4))
        valid = rng.uniform(size=(3, 4)) < 0.7
        c0 = 3.0
        r, k = hungarian(cost, valid, unassigned_cost=c0)
        n = len(r)
        total = cost[r.numpy(), k.numpy()].sum() + c0 * (3 - n) + c0 * (4 - n)
        assert total == pytest.approx(_brute(cost, valid, c0)[0])


def test_greedy_takes_cheapest_pairs_first():
    cost = torch.tensor([[1.0, 2.0], [1.5, 10.0]])
    r, k = greedy(cost)
    assert r.tolist() == [0, 1] and k.tolist() == [0, 1]  # greedy: (0,0) then (1,1)
    r, k = hungarian(cost)
    assert k.tolist() == [1, 0]  # optimum 2 + 1.5 < 1 + 10
    r, k = greedy(cost, unassigned_cost=4.0)  # pair (1,1) costs 10 >= 2*4: left out
    assert r.tolist() == [0] and k.tolist() == [0]


def test_batched_assign_equals_per_matrix_and_mask():
    g = torch.Generator().manual_seed(0)
    cost = torch.rand(2, 3, 4, 5, generator=g)
    valid = torch.rand(2, 3, 4, 5, generator=g) < 0.6
    out = assign(cost, valid)
    assert out.shape == (2, 3, 4)
    for a in range(2):
        for b in range(3):
            r, k = hungarian(cost[a, b], valid[a, b])
            ref = torch.full((4,), -1, dtype=torch.long)
            ref[r] = k
            assert torch.equal(out[a, b], ref)
    mask = out.unsqueeze(-1) == torch.arange(5)                 # one-hot (*, R, C)
    assert mask.sum(-1).le(1).all() and mask.sum(-2).le(1).all()
    assert not (mask & ~valid).any()


def test_assign_bad_input():
    with pytest.raises(TorchtrackError, match="method"):
        assign(torch.zeros(2, 2), method="auction")
    with pytest.raises(TorchtrackError, match="valid mask shape"):
        hungarian(np.zeros((2, 2)), np.zeros((3, 2), bool))


@pytest.mark.parametrize("seed", range(4))
def test_per_component_assignment_is_the_dense_optimum(seed):
    """Sparse pairs in clusters of every shape (1 x k, 2 x 2, ..., up to 9 x 9): the assignment built per
    connected component (enumerated or Hungarian) reaches the total of one dense Hungarian solve."""
    rng = np.random.default_rng(seed)
    n, m = 300, 280
    cluster_of_row, cluster_of_col = rng.integers(0, 60, n), rng.integers(0, 60, m)
    i, j = np.nonzero((cluster_of_row[:, None] == cluster_of_col[None, :]) & (rng.random((n, m)) < 0.7))
    score = rng.random(i.size)
    dense = np.zeros((n, m))
    dense[i, j] = score
    r, k = linear_sum_assignment(-dense)
    won = max_total_assignment(n, m, i, j, score)
    assert np.unique(i[won]).size == won.size and np.unique(j[won]).size == won.size  # one-to-one
    assert score[won].sum() == pytest.approx(dense[r, k].sum(), rel=1e-12)


