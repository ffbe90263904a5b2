"""The sparse GM-PHD update (gated pairs from a grid index) equals the dense all-pairs update (float64).

The reference below forms every (component, measurement) pair and follows the equations of the
``torchtrack.filters.gmphd.filter`` docstring with general solves, independently of the Cholesky and grid paths.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.association.grid import disc_candidates, nearest_within
from torchtrack.bench import scale
from torchtrack.filters.gmphd.birth import AdaptiveBirth
from torchtrack.filters.gmphd.filter import GMPHD, MixtureState, UpdateInfo
from torchtrack.filters.trackers.options import GMPHDBirthOptions, GMPHDFilterOptions
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.models import ConstantVelocity, LinearPosition

F64 = torch.float64


def dense_update(phd: GMPHD, state: MixtureState, z, mats, velocity=None, pair_loglik=None, label_index=None):
    """Every pair at once (eq. 25–29 of the module docstring); posterior pairs in (component, measurement) order."""
    H, R, gate, M = mats.H, mats.R, phd.gate, z.shape[0]
    log_kappa = mats.log_clutter.expand(M)
    robust = False
    if velocity is not None and mats.R_velocity is not None:
        z, H, R = torch.cat([z, velocity], 1), torch.eye(4, dtype=F64), mats.R_velocity
        log_kappa = log_kappa + mats.log_clutter_velocity
        robust = mats.log_velocity_outlier is not None
        gate = phd.gate if robust else phd.gate_velocity
    P, x = state.cov, state.mean
    live_w = torch.where(state.mask, state.log_weight, torch.full_like(state.log_weight, -math.inf))
    S = H @ P @ H.T + R                                                      # (J, m, m)
    nu = z.unsqueeze(0) - (x @ H.T).unsqueeze(1)                              # (J, M, m)

    def loglik(S_, nu_):
        nis = (nu_ * torch.linalg.solve(S_.unsqueeze(1), nu_.unsqueeze(-1)).squeeze(-1)).sum(-1)
        k = nu_.shape[-1]
        return nis, -0.5 * (nis + torch.logdet(S_).unsqueeze(1) + k * math.log(2 * math.pi))

    nis, log_g = loglik(S, nu)
    log_num = mats.log_p_detection + live_w.unsqueeze(1) + log_g
    p = mats.H.shape[0]
    if robust:
        nis_p, log_g_p = loglik(S[:, :p, :p], nu[..., :p])
        eps = mats.log_velocity_outlier.exp()
        with_v = log_num + torch.log1p(-eps)
        without_v = mats.log_p_detection + live_w.unsqueeze(1) + mats.log_velocity_outlier \
            + mats.log_clutter_velocity + log_g_p
        log_num, gated, use_pos = torch.logaddexp(with_v, without_v), nis_p <= gate, without_v > with_v
    else:
        gated = nis <= gate
    gated = gated & state.mask.unsqueeze(1)
    log_num = torch.where(gated, log_num, torch.full_like(log_num, -math.inf))
    if pair_loglik is not None:
        log_num = log_num + pair_loglik
    log_den = torch.logaddexp(log_kappa, torch.logsumexp(log_num, 0))
    jj, kk = gated.nonzero().unbind(1)
    K = torch.linalg.solve(S, H @ P).transpose(1, 2)                          # P Hᵀ S⁻¹
    mean = x[jj] + (K[jj] @ nu[jj, kk].unsqueeze(-1)).squeeze(-1)
    cov = P[jj] - K[jj] @ S[jj] @ K[jj].transpose(1, 2)
    if robust:
        Hp, Sp = H[:p], S[:, :p, :p]
        Kp = torch.linalg.solve(Sp, Hp @ P).transpose(1, 2)
        pos = use_pos[jj, kk]
        mean = torch.where(pos.unsqueeze(1), x[jj] + (Kp[jj] @ nu[jj, kk, :p].unsqueeze(-1)).squeeze(-1), mean)
        cov = torch.where(pos.view(-1, 1, 1), P[jj] - Kp[jj] @ Sp[jj] @ Kp[jj].transpose(1, 2), cov)
    post = MixtureState(torch.cat([live_w + mats.log_p_missed, log_num[jj, kk] - log_den[kk]]),
                        torch.cat([x, mean]), torch.cat([P, cov]), torch.cat([state.label, state.label[jj]]),
                        torch.cat([state.mask, torch.ones_like(jj, dtype=torch.bool)]))
    support = None
    if label_index is not None:
        support = torch.zeros(label_index[1], dtype=F64).index_add(
            0, label_index[0], (log_num - log_kappa).exp().sum(1))
    loglik_set = log_den.sum() - mats.p_detection * live_w.exp().sum()
    return post, UpdateInfo(loglik_set, log_den, int(jj.shape[0]), support)


def random_scene(seed: int, J: int = 300, M: int = 200, side: float = 250.0, dims: int = 2):
    """Components scattered over a square (covariances from tight to wide, a few dead slots) and measurements:
    half near components, half uniform."""
    g = torch.Generator().manual_seed(seed)
    n = 2 * dims
    mean = torch.cat([torch.rand(J, dims, generator=g, dtype=F64) * side,
                      torch.randn(J, dims, generator=g, dtype=F64) * 2], 1)
    A = torch.randn(J, n, n, generator=g, dtype=F64)
    spread = torch.rand(J, 1, 1, generator=g, dtype=F64).pow(3) * 40
    cov = A @ A.transpose(1, 2) * spread / n + 0.2 * torch.eye(n, dtype=F64)
    state = MixtureState(torch.rand(J, generator=g, dtype=F64).log(), mean, cov,
                         torch.randint(0, J // 3, (J,), generator=g), torch.rand(J, generator=g) > 0.05)
    near = mean[torch.randint(0, J, (M // 2,), generator=g), :dims] + torch.randn(M // 2, dims, generator=g,
                                                                                dtype=F64) * 3
    z = torch.cat([near, torch.rand(M - M // 2, dims, generator=g, dtype=F64) * side])
    v = torch.randn(M, dims, generator=g, dtype=F64) * 2
    return state, z, v


def make_phd(dims: int = 2, **kw) -> GMPHD:
    return GMPHD(ConstantVelocity(dims, q=0.5), LinearPosition(dims, sigma=1.3),
                 GMPHDFilterOptions(p_detection=0.85, clutter_density=1e-4, **kw)).double()


CASES = {
    "position": ({}, False),
    "velocity": ({"velocity_sigma": 0.8, "velocity_clutter_density": 0.01}, True),
    "velocity outlier": ({"velocity_sigma": 0.8, "velocity_clutter_density": 0.01, "velocity_outlier": 0.1}, True),
    "every pair in the gate": ({"gate_probability": 1.0}, False),
    "narrow gate": ({"gate_probability": 0.5}, False),
}


@pytest.fixture(params=["every pair", "grid"])
def pairs_from(request, monkeypatch) -> str:
    """Both ways to the gated pairs: every pair tested at once (a small problem) and the grid index."""
    limit = 10**12 if request.param == "every pair" else 0
    monkeypatch.setattr("torchtrack.filters.gmphd.filter.DENSE_PAIRS", limit)
    monkeypatch.setattr("torchtrack.filters.gmphd.birth.DENSE_PAIRS", limit)
    monkeypatch.setattr("torchtrack.association.grid.DENSE_PAIRS", limit)
    return request.param


def assert_same(a: tuple[MixtureState, UpdateInfo], b: tuple[MixtureState, UpdateInfo]) -> None:
    (pa, ia), (pb, ib) = a, b
    assert ia.gated_pairs == ib.gated_pairs
    assert torch.equal(pa.label, pb.label) and torch.equal(pa.mask, pb.mask)
    for x, y in [(pa.log_weight, pb.log_weight), (pa.mean, pb.mean), (pa.cov, pb.cov),
                 (ia.log_denominator, ib.log_denominator), (ia.log_likelihood, ib.log_likelihood)]:
        torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-10)
    if ia.label_support is not None:
        torch.testing.assert_close(ia.label_support, ib.label_support, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("seed", [0, 1])
def test_the_sparse_update_equals_the_dense_one(case, seed, pairs_from):
    options, with_velocity = CASES[case]
    phd = make_phd(**options)
    state, z, v = random_scene(seed)
    with torch.no_grad():
        mats = phd.matrices()
        velocity = v if with_velocity else None
        got = phd.update(state, z, mats, velocity=velocity)
        want = dense_update(phd, state, z, mats, velocity=velocity)
    assert got[1].gated_pairs > 50 and (case == "every pair in the gate" or got[1].gated_pairs < 300 * 200 / 4)
    assert_same(got, want)


def test_pair_ratios_and_label_support_follow_the_dense_update(pairs_from):
    """The per-pair log-ratio (a tone) enters each gated pair, the label support sums over the same pairs."""
    phd = make_phd()
    state, z, _ = random_scene(2)
    g = torch.Generator().manual_seed(3)
    ratio = torch.randn(state.size, z.shape[0], generator=g, dtype=F64)
    labels, index = torch.unique(state.label, return_inverse=True)
    with torch.no_grad():
        mats = phd.matrices()
        got = phd.update(state, z, mats, pair_loglik=lambda jj, kk: ratio[jj, kk],
                         label_index=(index, labels.shape[0]))
        want = dense_update(phd, state, z, mats, pair_loglik=ratio, label_index=(index, labels.shape[0]))
    assert_same(got, want)


def test_one_dimensional_measurements_use_the_same_grid(pairs_from):
    phd = make_phd(dims=1, velocity_sigma=None)
    state, z, _ = random_scene(4, dims=1)
    with torch.no_grad():
        mats = phd.matrices()
        got, want = phd.update(state, z, mats), dense_update(phd, state, z, mats)
    assert got[1].gated_pairs > 100
    assert_same(got, want)


@pytest.mark.parametrize("case", ["position", "velocity outlier"])
def test_gradients_equal_those_of_the_dense_update(case, pairs_from):
    """Through the gated pairs, the segment sums and the scatter of the label support: the gradients of the
    parameters and of the predicted mixture equal the dense update's."""
    options, with_velocity = CASES[case]
    phd = make_phd(**options)
    state, z, v = random_scene(5, J=120, M=80, side=120.0)
    mean, cov = state.mean.clone().requires_grad_(), state.cov.clone().requires_grad_()
    state = state._replace(mean=mean, cov=cov, mask=torch.ones_like(state.mask))   # dense: no −inf − −inf
    labels, index = torch.unique(state.label, return_inverse=True)
    grads = []
    for update in (phd.update, lambda *a, **k: dense_update(phd, *a, **k)):
        post, info = update(state, z, phd.matrices(), velocity=v if with_velocity else None,
                            label_index=(index, labels.shape[0]))
        loss = (info.log_likelihood + (post.log_weight.exp().unsqueeze(1) * post.mean).sum()
                + post.cov.diagonal(dim1=1, dim2=2).sum() + info.label_support.sum())
        inputs = [mean, cov, *phd.parameters()]
        grads.append([torch.zeros_like(x) if d is None else d
                      for x, d in zip(inputs, torch.autograd.grad(loss, inputs, allow_unused=True))])
    for a, b in zip(*grads):
        if a.dim() == 3:              # of a symmetric P only the symmetric part is defined (Cholesky reads one half)
            a, b = a + a.transpose(1, 2), b + b.transpose(1, 2)
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
    assert sum(float(a.abs().sum()) for a in grads[0]) > 0


def test_disc_candidates_hold_every_pair_within_the_radius():
    g = torch.Generator().manual_seed(7)
    center = torch.rand(400, 2, generator=g, dtype=F64) * 300 - 20           # some beside the points' square
    radius = torch.rand(400, generator=g, dtype=F64).pow(4) * 60
    radius[:5], radius[5:10] = -1.0, math.inf                                   # empty and unbounded queries
    points = torch.rand(500, 2, generator=g, dtype=F64) * 260
    qq, pp = disc_candidates(center, radius, points)
    found = set(zip(qq.tolist(), pp.tolist()))
    within = (torch.cdist(center, points) <= radius.unsqueeze(1)).nonzero().tolist()
    assert len(within) > 1000 and {tuple(x) for x in within} <= found
    assert not (qq < 5).any() and (torch.bincount(qq, minlength=400)[5:10] == 500).all()
    assert len(found) == qq.numel() and len(found) < 0.1 * 400 * 500        # no duplicate; sparse
    assert torch.equal(qq, torch.sort(qq).values)


def test_birth_measurements_equal_the_distance_to_every_heavy_prediction(pairs_from):
    birth = AdaptiveBirth(GMPHDBirthOptions(distance_threshold=5.0, suppress_weight=0.1))
    g = torch.Generator().manual_seed(8)
    pos = torch.rand(2000, 2, generator=g, dtype=F64) * 500
    log_w = torch.rand(2000, generator=g, dtype=F64).log() * 2
    z = torch.cat([pos[:300] + torch.randn(300, 2, generator=g, dtype=F64) * 4,
                   torch.rand(300, 2, generator=g, dtype=F64) * 500])
    d = torch.cdist(z, pos).masked_fill(~(log_w > math.log(0.1)).unsqueeze(0), math.inf)
    want = d.min(1).values > 5.0
    assert 50 < int(want.sum()) < 550
    assert torch.equal(birth.birth_measurements(pos, log_w, z), want)


def test_the_nearest_detection_is_that_of_every_distance(pairs_from):
    """The tone update's nearest detection within 3 px (the lowest index among equals)."""
    g = torch.Generator().manual_seed(9)
    z = torch.rand(800, 2, generator=g, dtype=F64) * 400
    z[1] = z[0]                                                                   # equal distances
    pos = torch.cat([z[:400] + torch.randn(400, 2, generator=g, dtype=F64) * 2,
                     torch.rand(200, 2, generator=g, dtype=F64) * 400])
    hit, k = nearest_within(pos, z, 3.0)
    d = torch.cdist(pos, z)
    near, want = d.min(1)
    assert torch.equal(hit, near <= 3.0) and 200 < int(hit.sum()) < 590
    assert torch.equal(k[hit], want[hit]) and not (k[hit] == 1).any()


@pytest.mark.parametrize("name", ["gmphd", "labelled-gmphd"])
def test_trackers_report_what_the_dense_update_reports(name, monkeypatch):
    """A 300-vehicle scene at the bench's density, float64: the sparse and the dense update give the same
    tracks, enhanced and labelled."""
    scene = scale.simulate(300, 8, seed=2)
    runs = []
    for dense in (False, True):
        if dense:
            monkeypatch.setattr(GMPHD, "update", lambda self, state, z, mats, velocity=None, **kw: dense_update(
                self, state, z, mats, velocity, None, kw.get("label_index")))
        tracker = make_tracker(name, {"dtype": "float64"})
        runs.append([tracker.step(frame, z, v) for frame, z, v in scene.detections])
    for (ids_a, pos_a), (ids_b, pos_b) in zip(*runs):
        assert torch.equal(ids_a, ids_b)
        torch.testing.assert_close(pos_a, pos_b, rtol=0, atol=1e-8)
    assert sum(ids.numel() for ids, _ in runs[0]) > 300 * 5


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (runs where a GPU exists)")
@pytest.mark.parametrize("name", ["gmphd", "labelled-gmphd"])
def test_the_grid_path_on_cuda_gives_the_cpu_tracks(name, monkeypatch):
    monkeypatch.setattr("torchtrack.filters.gmphd.filter.DENSE_PAIRS", 0)
    monkeypatch.setattr("torchtrack.filters.gmphd.birth.DENSE_PAIRS", 0)
    scene = scale.simulate(300, 6, seed=3)
    runs = {}
    for device in ("cpu", "cuda"):
        tracker = make_tracker(name, {"dtype": "float64"})
        runs[device] = [tracker.step(frame, z.to(device), v.to(device)) for frame, z, v in scene.detections]
    for (ids_cpu, pos_cpu), (ids_gpu, pos_gpu) in zip(runs["cpu"], runs["cuda"]):
        assert ids_gpu.device.type == "cuda"
        assert torch.equal(ids_cpu, ids_gpu.cpu())
        torch.testing.assert_close(pos_gpu.cpu(), pos_cpu, rtol=0, atol=1e-6)
