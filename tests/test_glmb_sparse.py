"""The GLMB's sparse gating and grouping against independent dense references (float64): the candidate table of
the grid path against brute force over every row–measurement pair, the groups against a union-find over the
dense label × measurement gating matrix, and the tracker with the grid path forced against the all-pairs one."""

import math

import numpy as np
import pytest
import torch

import torchtrack.filters.glmb.gating as glmb_gating
from torchtrack.association.gibbs import FIRST_MEASUREMENT, gating_groups
from torchtrack.filters.glmb.gating import gated_candidates
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.gaussian import chi2_quantile, innovation_cov, kalman_gain


def _scene(rng, n_rows, n_meas, m, extent):
    """Predicted rows with random covariances and measurements around a share of them."""
    mean = np.c_[rng.uniform(0, extent, (n_rows, 2)), rng.normal(0, 2, (n_rows, 2))]
    A = rng.normal(0, 1, (n_rows, 4, 4))
    cov = A @ A.transpose(0, 2, 1) + np.diag([1.0, 1.0, 0.5, 0.5])
    H = np.eye(4)[:m]
    R = np.diag([1.0, 1.0, 2.0, 2.0][:m])
    near = mean[rng.integers(0, n_rows, n_meas // 2), :m] + rng.normal(0, 2, (n_meas // 2, m))
    far = np.c_[rng.uniform(0, extent, (n_meas - n_meas // 2, 2)), rng.normal(0, 2, (n_meas - n_meas // 2, m - 2))]
    return mean, cov, H, R, np.r_[near, far]


def _brute_force(mean, cov, H, R, z, gate):
    """Per row: the gated measurements by decreasing likelihood and their log-likelihoods (numpy solves)."""
    rows = []
    for x, P in zip(mean, cov):
        S = H @ P @ H.T + R
        nu = z - H @ x
        nis = np.einsum("ki,ki->k", nu, np.linalg.solve(S, nu.T).T)
        loglik = -0.5 * (nis + np.linalg.slogdet(S)[1] + z.shape[1] * math.log(2 * math.pi))
        inside = np.nonzero(nis <= gate)[0]
        order = inside[np.argsort(-loglik[inside], kind="stable")]
        rows.append((order, loglik[order]))
    return rows


def _candidates(mean, cov, H, R, z, gate, dense):
    t = {k: torch.from_numpy(v) for k, v in dict(mean=mean, cov=cov, H=H, R=R, z=z).items()}
    C, S = innovation_cov(t["cov"], t["H"], t["R"])
    return gated_candidates(t["mean"] @ t["H"].T, S, kalman_gain(S, C), t["z"], gate, dense)


@pytest.mark.parametrize("m", [2, 4])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_candidates_equal_brute_force(m, seed):
    rng = np.random.default_rng(seed)
    mean, cov, H, R, z = _scene(rng, 300, 400, m, 400.0)
    gate = chi2_quantile(0.999, m)
    truth = _brute_force(mean, cov, H, R, z, gate)
    assert sum(len(o) for o, _ in truth) > 300                         # many gated pairs, several per row
    for dense in (True, False):
        cand, vals = _candidates(mean, cov, H, R, z, gate, dense)
        assert cand.shape[1] == max(len(o) for o, _ in truth)
        for i, (order, loglik) in enumerate(truth):
            k = len(order)
            assert cand[i, :k].tolist() == order.tolist(), (dense, i)
            assert (cand[i, k:] == -1).all() and torch.isinf(vals[i, k:]).all()
            np.testing.assert_allclose(vals[i, :k].numpy(), loglik, rtol=0, atol=1e-9)


def test_grid_candidates_of_empty_frames():
    rng = np.random.default_rng(3)
    mean, cov, H, R, z = _scene(rng, 5, 4, 2, 50.0)
    for dense in (True, False):
        cand, vals = _candidates(mean, cov, H, R, z[:0], 9.0, dense)
        assert cand.shape == vals.shape == (5, 0)
        cand, vals = _candidates(mean[:0], cov[:0], H, R, z, 9.0, dense)
        assert cand.shape == vals.shape == (0, 0)


def _union_find_groups(cand, slot_of_row, n_slots, n_meas):
    """Groups of slots from the dense slot × measurement gating matrix, by union-find over slots."""
    gated = np.zeros((n_slots, n_meas), bool)
    for r, row in enumerate(cand):
        gated[slot_of_row[r], row[row >= 0]] = True
    parent = list(range(n_slots))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for j in range(n_meas):
        holders = np.nonzero(gated[:, j])[0]
        for s in holders[1:]:
            parent[find(s)] = find(holders[0])
    groups = {}
    for s in range(n_slots):
        groups.setdefault(find(s), []).append(s)
    return sorted(groups.values()), gated


@pytest.mark.parametrize("seed", range(5))
def test_groups_equal_dense_components(seed):
    rng = np.random.default_rng(seed)
    n_rows, n_meas, n_slots = 200, 150, 160
    slot_of_row = np.r_[np.arange(n_slots), rng.integers(0, n_slots, n_rows - n_slots)]   # some alternative rows
    cand = np.full((n_rows, 4), -1)
    for r in range(n_rows):
        k = rng.integers(0, 4)
        cand[r, :k] = rng.choice(n_meas, k, replace=False)
    groups = gating_groups(torch.from_numpy(cand), torch.from_numpy(slot_of_row), n_slots, n_meas)
    truth, gated = _union_find_groups(cand, slot_of_row, n_slots, n_meas)
    slots = groups.slots.numpy()
    found = sorted(sorted(int(s) for s in g if s < n_slots) for g in slots)
    assert found == truth
    for g, row in enumerate(slots):                          # sweep order, positions and group ids agree
        for p, s in enumerate(row):
            if s < n_slots:
                assert groups.group_of_slot[s] == g and groups.position[s] == p
    for p, w in enumerate(groups.widths):                    # each step's columns hold its slots' candidates
        on_step = [s for s in range(n_slots) if groups.position[s] == p]
        assert w == FIRST_MEASUREMENT + max((cand[slot_of_row == s] >= 0).sum(1).max() for s in on_step)
    # local measurement indices: distinct within a group, ascending with the global index, below group_meas
    for g in range(slots.shape[0]):
        members = [s for s in slots[g] if s < n_slots]
        meas = np.nonzero(gated[members].any(0))[0]
        assert groups.local_meas[meas].tolist() == list(range(len(meas)))
        assert len(meas) <= groups.group_meas


def test_tracker_with_grid_gating_reports_the_same_tracks(monkeypatch):
    """A 60-vehicle scene with clutter: the tracker with every frame through the grid path reports the same ids
    and positions as with the all-pairs path."""
    rng = np.random.default_rng(4)
    start = rng.uniform(0, 500, (60, 2))
    velocity = rng.normal(0, 2, (60, 2))
    frames = []
    for k in range(12):
        truth = start + k * velocity
        seen = truth[rng.random(60) < 0.9]
        z = np.r_[seen + rng.normal(0, 1, seen.shape), rng.uniform(0, 500, (20, 2))]
        frames.append(torch.from_numpy(z))

    def run():
        tracker = make_tracker("glmb", {"clutter_density": 1e-4, "seed": 3})
        return [tracker.step(k + 1, z) for k, z in enumerate(frames)]

    dense = run()
    monkeypatch.setattr(glmb_gating, "DENSE_PAIRS", 0)
    sparse = run()
    assert sum(ids.shape[0] for ids, _ in dense) > 100
    for (ids_d, pos_d), (ids_s, pos_s) in zip(dense, sparse):
        assert torch.equal(ids_d, ids_s)
        torch.testing.assert_close(pos_s, pos_d, rtol=0, atol=1e-9)


def _sequential_products(proj, proj_w, proj_q, pair_new, cap):
    """Per joined group (ascending), its factors (pairs ascending) multiplied one after another in Python, the
    product truncated to its ``cap`` heaviest (heaviest first) after each factor."""
    out = []
    for g in sorted(set(pair_new.tolist())):
        pairs = [q for q in range(len(pair_new)) if pair_new[q] == g]
        if len(pairs) < 2:
            continue
        prod = [((), 0.0)]
        for q in pairs:
            factor = [(tuple(int(x) for x in proj[r] if x >= 0), float(proj_w[r]))
                      for r in range(len(proj_q)) if proj_q[r] == q]
            prod = [(a + b, wa + wb) for a, wa in prod for b, wb in factor]
            if len(prod) > cap:
                prod = sorted(prod, key=lambda item: -item[1])[:cap]
        out += [(g, tuple(sorted(rows)), w) for rows, w in prod]
    return out


@pytest.mark.parametrize("seed", range(4))
def test_products_of_joined_groups_equal_sequential_products(seed):
    from torchtrack.filters.glmb.filter import _products

    rng = np.random.default_rng(seed)
    n_groups = 12
    pair_new = torch.from_numpy(np.sort(rng.integers(0, n_groups, 25)))
    proj_q, proj, next_row = [], [], 0
    for q in range(pair_new.shape[0]):
        for _ in range(rng.integers(1, 5)):                     # 1-4 hypotheses per factor, 0-2 rows each
            k = int(rng.integers(0, 3))
            proj.append(list(range(next_row, next_row + k)) + [-1] * (2 - k))
            proj_q.append(q)
            next_row += k
    proj, proj_q = torch.tensor(proj), torch.tensor(proj_q)
    proj_w = torch.from_numpy(rng.normal(0, 3, proj.shape[0]))
    factors = torch.bincount(pair_new, minlength=n_groups)
    for cap in (3, 8, 1000):
        hyp, log_w, group, capped = _products(proj, proj_w, proj_q, pair_new, factors, cap)
        truth = _sequential_products(proj, proj_w, proj_q, pair_new, cap)
        assert len(truth) == hyp.shape[0] > 0
        for (g, rows, w), h, lw, gg in zip(truth, hyp, log_w, group):
            assert int(gg) == g and tuple(int(x) for x in h if x >= 0) == rows
            assert float(lw) == pytest.approx(w, abs=1e-12)
        assert capped == (cap < 1000)
