"""OSPA and GOSPA: hand-worked cases, brute force over assignments, batching with masks, gradients."""

import itertools
import math

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.metrics.ospa import gospa, ospa


def t(rows):
    return torch.tensor(rows, dtype=torch.float64).reshape(-1, 2)


def test_both_empty_is_zero():
    r = ospa(t([]), t([]), c=5.0)
    assert float(r.total) == 0 and float(r.cardinality) == 0
    g = gospa(t([]), t([]), c=5.0)
    assert float(g.total) == 0 and float(g.num_missed) == 0 and float(g.num_false) == 0


def test_one_empty_set():
    Y = t([[1, 1], [2, 2], [3, 3]])
    assert float(ospa(t([]), Y, c=7.0, p=2).total) == pytest.approx(7.0)
    g = gospa(t([]), Y, c=7.0, p=2)  # three false targets at c^p/2 each
    assert float(g.false) == pytest.approx(3 * 49 / 2)
    assert float(g.total) == pytest.approx(math.sqrt(3 * 49 / 2))
    g = gospa(Y, t([]), c=7.0, p=2)
    assert float(g.missed) == pytest.approx(3 * 49 / 2) and float(g.num_missed) == 3


def test_unequal_cardinalities_hand_worked():
    X, Y = t([[0, 0], [10, 0]]), t([[3, 4]])
    r = ospa(X, Y, c=20.0, p=1)  # (1/2) (5 + 20)
    assert float(r.total) == pytest.approx(12.5)
    assert float(r.localisation) == pytest.approx(2.5) and float(r.cardinality) == pytest.approx(10.0)
    r = ospa(X, Y, c=20.0, p=2)  # sqrt((25 + 400) / 2)
    assert float(r.total) == pytest.approx(math.sqrt(212.5))
    g = gospa(X, Y, c=20.0, p=1)  # 5 + 20/2
    assert (float(g.total), float(g.localisation), float(g.missed), float(g.false)) == pytest.approx(
        (15.0, 5.0, 10.0, 0.0))


def test_cut_off():
    X, Y = t([[0, 0], [100, 0]]), t([[0, 3], [100, 50]])
    r = ospa(X, Y, c=10.0, p=1)  # (3 + 10) / 2: the far pair is cut at c
    assert float(r.total) == pytest.approx(6.5)
    g = gospa(X, Y, c=10.0, p=1)  # the far pair is one missed and one false target: 3 + 5 + 5
    assert (float(g.total), float(g.num_missed), float(g.num_false)) == pytest.approx((13.0, 1.0, 1.0))
    assert float(ospa(t([[0, 0]]), t([[50, 50]]), c=4.0, p=3).total) == pytest.approx(4.0)


def brute_ospa(X, Y, c, p):
    n, m = len(X), len(Y)
    if n == 0 and m == 0:
        return 0.0
    if n > m:
        X, Y, n, m = Y, X, m, n
    best = min(sum(min(math.dist(X[i], Y[k]), c) ** p for i, k in enumerate(perm))
               for perm in itertools.permutations(range(m), n))
    return ((best + c**p * (m - n)) / m) ** (1 / p)


def brute_gospa(X, Y, c, p):
    """Eq. (2) literally: every partial assignment with pairs closer than c."""
    n, m = len(X), len(Y)
    best = math.inf
    for size in range(min(n, m) + 1):
        for xs in itertools.combinations(range(n), size):
            for ys in itertools.permutations(range(m), size):
                d = [math.dist(X[i], Y[k]) for i, k in zip(xs, ys)]
                if all(v < c for v in d):
                    best = min(best, sum(v**p for v in d) + c**p / 2 * (n + m - 2 * size))
    return best ** (1 / p)


@pytest.mark.parametrize("seed", range(6))
def test_brute_force_batched_with_masks(seed):
    g = torch.Generator().manual_seed(seed)
    T, N, M = 5, 4, 5
    X = torch.rand(T, N, 2, generator=g, dtype=torch.float64) * 10
    Y = torch.rand(T, M, 2, generator=g, dtype=torch.float64) * 10
    xm = torch.rand(T, N, generator=g) < 0.7
    ym = torch.rand(T, M, generator=g) < 0.6
    c, p = 4.0, [1, 2, 3][seed % 3]
    r = ospa(X, Y, c=c, p=p, x_mask=xm, y_mask=ym)
    q = gospa(X, Y, c=c, p=p, x_mask=xm, y_mask=ym)
    assert r.total.shape == (T,) and q.total.shape == (T,)
    for k in range(T):
        xs, ys = X[k][xm[k]].tolist(), Y[k][ym[k]].tolist()
        assert float(r.total[k]) == pytest.approx(brute_ospa(xs, ys, c, p))
        assert float(q.total[k]) == pytest.approx(brute_gospa(xs, ys, c, p))
        parts = q.localisation[k] + q.missed[k] + q.false[k]
        assert float(parts) == pytest.approx(float(q.total[k]) ** p)
        assert float(q.num_missed[k]) - float(q.num_false[k]) == len(xs) - len(ys)
    means = q.mean()
    assert means["total"] == pytest.approx(float(q.total.mean()))


def test_gospa_alpha_other_than_two():
    X, Y = t([[0, 0], [10, 0]]), t([[3, 4]])
    g = gospa(X, Y, c=20.0, p=1, alpha=1.0)  # 5 + 20/1
    assert float(g.total) == pytest.approx(25.0) and math.isnan(float(g.missed))
    with pytest.raises(TorchtrackError, match="alpha"):
        gospa(X, Y, c=1.0, alpha=3.0)


def test_gradient_flows_through_assigned_pairs():
    X = t([[0.3, 0.1], [5.0, 5.0]]).requires_grad_()
    Y = t([[1.0, 0.0], [5.5, 4.0], [9.0, 9.0]])
    assert torch.autograd.gradcheck(lambda x: gospa(x, Y, c=3.0, p=2).total, (X,))
    assert torch.autograd.gradcheck(lambda x: ospa(x, Y, c=3.0, p=2).total, (X,))


def test_bad_shapes():
    with pytest.raises(TorchtrackError, match="share d"):
        ospa(torch.zeros(3, 2), torch.zeros(3, 3), c=1.0)
    with pytest.raises(TorchtrackError, match="c > 0"):
        ospa(torch.zeros(3, 2), torch.zeros(3, 2), c=0.0)


def test_per_frame_on_mot_data_matches_direct_and_chunks(monkeypatch):
    import importlib

    import numpy as np

    from torchtrack.io.mot import from_points
    from torchtrack.metrics.ospa import mot_ospa_gospa

    rng = np.random.default_rng(0)
    gt = from_points(rng.integers(1, 8, 40), np.arange(40), rng.uniform(0, 30, 40), rng.uniform(0, 30, 40))
    pred = from_points(rng.integers(3, 11, 30), np.arange(30), rng.uniform(0, 30, 30), rng.uniform(0, 30, 30))
    frames, o, g = mot_ospa_gospa(gt, pred, c=6.0, p_ospa=1.0, p_gospa=2.0)
    np.testing.assert_array_equal(frames, np.union1d(gt.frame, pred.frame))
    for k, f in enumerate(frames):
        a = torch.from_numpy(gt.centers()[gt.frame == f])
        b = torch.from_numpy(pred.centers()[pred.frame == f])
        assert float(o.total[k]) == pytest.approx(brute_ospa(a.tolist(), b.tolist(), 6.0, 1.0))
        assert float(g.total[k]) == pytest.approx(float(gospa(a, b, 6.0, 2.0).total))
    module = importlib.import_module("torchtrack.metrics.ospa")
    monkeypatch.setattr(module, "MAX_PAIRS", 40)  # forces chunks of a frame or two
    _, o2, g2 = mot_ospa_gospa(gt, pred, c=6.0)
    torch.testing.assert_close(o2.total, o.total)
    torch.testing.assert_close(g2.missed, g.missed)
