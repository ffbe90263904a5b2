"""GM-PHD core: Kalman reduction, cardinality, merging, gradients (float64)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter as FPKalman

from torchtrack.errors import TorchtrackError
from torchtrack.filters.gmphd.birth import AdaptiveBirth
from torchtrack.filters.gmphd.filter import GMPHD, MixtureState, merge
from torchtrack.filters.gmphd.tracker import GMPHDTracker
from torchtrack.filters.trackers.options import GMPHDBirthOptions, GMPHDConfig, GMPHDFilterOptions
from torchtrack.models import ConstantVelocity, LinearPosition

F64 = torch.float64


def one(mean, cov, w=1.0, label=1) -> MixtureState:
    return MixtureState(torch.tensor([math.log(w)], dtype=F64), torch.as_tensor(mean, dtype=F64)[None],
                        torch.as_tensor(cov, dtype=F64)[None], torch.tensor([label]), torch.tensor([True]))


def make_phd(q=0.5, sigma=1.5, pd=0.9, kappa=1e-4, **kw) -> GMPHD:
    return GMPHD(ConstantVelocity(2, q=q), LinearPosition(2, sigma=sigma),
                 GMPHDFilterOptions(p_detection=pd, clutter_density=kappa, **kw)).double()


def test_single_target_pd1_no_clutter_is_the_kalman_filter():
    """p_D → 1, κ → 0, one target: the detected component is the Kalman posterior (FilterPy) with weight 1."""
    phd = make_phd(pd=1 - 1e-6, kappa=1e-30, p_survival=1 - 1e-6, gate_probability=1.0)
    mats = phd.matrices(1.0)
    g = torch.Generator().manual_seed(3)
    m0, P0 = np.array([10.0, -5.0, 1.0, 0.5]), np.diag([4.0, 4.0, 1.0, 1.0])
    state = one(m0, P0)
    ref = FPKalman(dim_x=4, dim_z=2)
    ref.x, ref.P = m0.copy(), P0.copy()
    ref.F, ref.Q = mats.F.numpy(), mats.Q.detach().numpy()
    ref.H, ref.R = mats.H.numpy(), mats.R.detach().numpy()
    truth = torch.tensor(m0)
    for _ in range(15):
        truth = mats.F @ truth
        z = truth[:2] + 1.5 * torch.randn(2, generator=g, dtype=F64)
        post, info = phd.update(phd.predict(state, mats), z[None], mats)
        post = phd.prune(post)
        assert post.size == 1
        ref.predict()
        ref.update(z.numpy())
        np.testing.assert_allclose(post.mean[0].detach().numpy(), ref.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(post.cov[0].detach().numpy(), ref.P, rtol=1e-8, atol=1e-10)
        assert float(post.log_weight.detach().exp()[0]) == pytest.approx(1.0, abs=1e-9)
        # the PHD likelihood reduces to the Kalman innovation likelihood (−p_D Σw + log p_D g)
        assert float(info.log_likelihood.detach()) == pytest.approx(ref.log_likelihood - 1.0, abs=1e-4)
        state = post


def _random_mixture(g, J, scale):
    """``J`` random 4-D components (means of size ``scale``, covariances ``A Aᵀ + I``, weights in [0.2, 1.2])."""
    mean = torch.randn(J, 4, generator=g, dtype=F64) * scale
    A = torch.randn(J, 4, 4, generator=g, dtype=F64)
    cov = A @ A.transpose(-1, -2) + torch.eye(4, dtype=F64)
    w = torch.rand(J, generator=g, dtype=F64) + 0.2
    return MixtureState(w.log(), mean, cov, torch.arange(J), torch.ones(J, dtype=torch.bool)), mean, cov, w


def test_update_matches_textbook_weights_brute_force():
    """Weights of the batched update equal the per-pair formula of Vo & Ma (2006, eq. 25–29)."""
    phd = make_phd(pd=0.8, kappa=2e-3, gate_probability=1.0)
    mats = phd.matrices(1.0)
    g = torch.Generator().manual_seed(0)
    J, M = 4, 5
    state, mean, cov, w = _random_mixture(g, J, 3.0)
    z = torch.randn(M, 2, generator=g, dtype=F64) * 3
    post, _ = phd.update(state, z, mats)
    H, R = mats.H, mats.R.detach()
    q = torch.zeros(J, M, dtype=F64)
    for j in range(J):
        S = H @ cov[j] @ H.T + R
        q[j] = torch.distributions.MultivariateNormal(H @ mean[j], S).log_prob(z).exp()
    pd, kappa = phd.p_detection().detach(), phd.clutter_density().detach()   # 0.8 and 2e-3 (float32-rounded)
    num = pd * w[:, None] * q
    expected = num / (kappa + num.sum(0, keepdim=True))
    got = post.log_weight[J:].exp().detach().reshape(J, M)     # all pairs gated (γ = ∞), row-major order
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(post.log_weight[:J].exp().detach(), (1 - pd) * w)


def _sequential_merge(w, m, P, U):
    """Reference: Vo & Ma's sequential greedy merge (Table II)."""
    idx = list(np.argsort(-w))
    out = []
    alive = set(idx)
    while alive:
        j = max(alive, key=lambda i: w[i])
        group = [i for i in alive if (m[i] - m[j]) @ np.linalg.solve(P[i], m[i] - m[j]) <= U]
        ws = w[group].sum()
        mu = (w[group, None] * m[group]).sum(0) / ws
        out.append((ws, mu))
        alive -= set(group)
    return sorted(out, key=lambda t: -t[0])


def test_merge_agrees_with_sequential_greedy_on_clusters():
    g = torch.Generator().manual_seed(1)
    centres = torch.tensor([[0.0, 0, 0, 0], [30, 0, 1, 0], [0, 40, 0, -1], [60, 60, 2, 2]], dtype=F64)
    mean = (centres[:, None, :] + 0.2 * torch.randn(4, 5, 4, generator=g, dtype=F64)).reshape(-1, 4)
    cov = torch.eye(4, dtype=F64).expand(20, 4, 4).clone()
    w = torch.rand(20, generator=g, dtype=F64) * 0.5 + 0.01
    state = MixtureState(w.log(), mean, cov, torch.arange(20), torch.ones(20, dtype=torch.bool))
    merged = merge(state, 4.0)
    ref = _sequential_merge(w.numpy(), mean.numpy(), cov.numpy(), 4.0)
    assert merged.size == len(ref) == 4
    order = torch.argsort(merged.log_weight, descending=True)
    for k, (ws, mu) in zip(order.tolist(), ref):
        assert float(merged.log_weight[k].exp()) == pytest.approx(ws, rel=1e-12)
        np.testing.assert_allclose(merged.mean[k].numpy(), mu, atol=1e-12)
    # total mass is conserved and each label is its group leader's (the heaviest member)
    assert float(merged.log_weight.exp().sum()) == pytest.approx(float(w.sum()), rel=1e-12)
    for k in range(4):
        members = (mean - merged.mean[k]).norm(dim=1) < 5
        assert int(merged.label[k]) == int(torch.arange(20)[members][w[members].argmax()])


def test_expected_cardinality_tracks_true_count():
    """Static scene, N targets, p_D 0.9, Poisson clutter: mean Σw in steady state ≈ N within MC error."""
    N, runs, T, clutter, side = 6, 12, 25, 8.0, 200.0
    g = torch.Generator().manual_seed(7)
    kappa = clutter / side**2
    counts = []
    for _ in range(runs):
        phd = make_phd(q=0.1, sigma=1.0, pd=0.9, kappa=kappa, p_survival=0.999)
        mats = phd.matrices(1.0)
        pos = torch.rand(N, 2, generator=g, dtype=F64) * side
        truth = torch.cat([pos, torch.randn(N, 2, generator=g, dtype=F64)], 1)
        state = MixtureState(torch.zeros(N, dtype=F64), truth + torch.randn(N, 4, generator=g, dtype=F64),
                             torch.diag(torch.tensor([2.0, 2, 1, 1], dtype=F64)).expand(N, 4, 4).clone(),
                             torch.arange(N), torch.ones(N, dtype=torch.bool))
        run_counts = []
        for t in range(T):
            truth = truth @ mats.F.T
            det = torch.rand(N, generator=g) < 0.9
            z = truth[det, :2] + torch.randn(int(det.sum()), 2, generator=g, dtype=F64)
            nc = int(torch.poisson(torch.tensor(clutter), generator=g))
            z = torch.cat([z, torch.rand(nc, 2, generator=g, dtype=F64) * side])
            with torch.no_grad():
                state, _ = phd.update(phd.predict(state, mats), z, mats)
                state = phd.reduce(state)
            if t >= 5:
                run_counts.append(float(state.expected_count()))
        counts.append(np.mean(run_counts))
    counts = np.array(counts)
    se = counts.std(ddof=1) / math.sqrt(runs)
    assert abs(counts.mean() - N) < 3 * se + 0.05 * N, (counts.mean(), se)


def test_gradients_reach_pd_kappa_q_r_and_birth_weight():
    tracker = GMPHDTracker(GMPHD(ConstantVelocity(2, q=0.5), LinearPosition(2, sigma=1.0),
                                 GMPHDFilterOptions(area=1e4)),
                           AdaptiveBirth(GMPHDBirthOptions(birth_weight=0.05)), GMPHDConfig(dtype="float64"))
    g = torch.Generator().manual_seed(0)
    p = torch.tensor([[20.0, 30.0], [60.0, 50.0]], dtype=F64)
    v = torch.tensor([[1.0, 0.5], [-0.5, 1.0]], dtype=F64)
    zs, vs = [], []
    for t in range(6):
        pt = p + v * t
        zs.append(torch.cat([pt + 0.5 * torch.randn(2, 2, generator=g, dtype=F64),
                             torch.rand(2, 2, generator=g, dtype=F64) * 100]))
        vs.append(torch.cat([v, torch.zeros(2, 2, dtype=F64)]))
    ll = tracker.log_likelihood(zs, vs).sum()
    ll.backward()
    params = {"p_D": tracker.phd.p_detection.raw, "kappa": tracker.phd.clutter_density.raw,
              "Q": tracker.phd.motion.q.raw, "R": tracker.phd.measurement.sigma.raw,
              "birth weight": tracker.birth.birth_weight.raw, "p_S": tracker.phd.p_survival.raw}
    for name, prm in params.items():
        assert prm.grad is not None and torch.isfinite(prm.grad).all() and prm.grad.abs().sum() > 0, name

    # the gradient is the derivative of the (piecewise smooth) likelihood: central differences agree
    def value(delta):
        with torch.no_grad():
            tracker.phd.p_detection.raw += delta
            out = float(tracker.log_likelihood(zs, vs).sum())
            tracker.phd.p_detection.raw -= delta
        return out

    h = 1e-6
    fd = (value(h) - value(-h)) / (2 * h)
    assert float(tracker.phd.p_detection.raw.grad) == pytest.approx(fd, rel=1e-5, abs=1e-6)


def test_velocity_update_matches_the_four_dimensional_textbook_update():
    """With ``velocity_sigma`` each detection is ``[z, v]`` measured by ``H = I_4``, ``R_4 = blockdiag(R, σ_v² I)``
    and clutter ``κ κ_v``: weights and means equal the per-pair Vo & Ma formulas in four dimensions."""
    phd = make_phd(pd=0.8, kappa=2e-3, gate_probability=1.0, velocity_sigma=0.7, velocity_clutter_density=0.01)
    mats = phd.matrices(1.0)
    g = torch.Generator().manual_seed(5)
    J, M = 3, 4
    state, mean, cov, w = _random_mixture(g, J, 2.0)
    z = torch.randn(M, 2, generator=g, dtype=F64) * 2
    v = torch.randn(M, 2, generator=g, dtype=F64)
    post, info = phd.update(state, z, mats, velocity=v)
    zz = torch.cat([z, v], 1)
    s_z, s_v = phd.measurement.sigma().detach(), phd.velocity_sigma().detach()   # 1.5, 0.7 (float32-rounded)
    R4 = torch.diag(torch.stack([s_z, s_z, s_v, s_v]).reshape(4) ** 2)
    q = torch.zeros(J, M, dtype=F64)
    upd = torch.zeros(J, M, 4, dtype=F64)
    for j in range(J):
        S = cov[j] + R4
        q[j] = torch.distributions.MultivariateNormal(mean[j], S).log_prob(zz).exp()
        K = cov[j] @ torch.linalg.inv(S)
        upd[j] = mean[j] + (zz - mean[j]) @ K.T
    pd = phd.p_detection().detach()
    clutter = phd.clutter_density().detach() * phd.velocity_clutter_density().detach()
    num = pd * w[:, None] * q
    expected = num / (clutter + num.sum(0, keepdim=True))
    torch.testing.assert_close(post.log_weight[J:].exp().detach().reshape(J, M), expected, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(post.mean[J:].detach().reshape(J, M, 4), upd, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(info.log_denominator.detach(), torch.log(clutter + num.sum(0)), rtol=1e-9, atol=1e-9)
    # without velocities the same filter is the position-only update
    post2, _ = phd.update(state, z, mats)
    ref, _ = make_phd(pd=0.8, kappa=2e-3, gate_probability=1.0).update(state, z, mats._replace(R_velocity=None))
    torch.testing.assert_close(post2.log_weight, ref.log_weight)


def test_velocity_outliers_mix_the_velocity_and_position_only_updates():
    """With ``velocity_outlier`` ε each pair's likelihood is ``(1−ε) N([z, v]) + ε κ_v N(z)`` (gated on the
    position); the posterior takes the update of the larger term. Checked per pair against the textbook
    formulas, and a grossly wrong velocity still gives its target a detection at the measured position."""
    eps, kv = 0.2, 0.01
    phd = make_phd(pd=0.8, kappa=2e-3, gate_probability=1.0, velocity_sigma=0.7, velocity_clutter_density=kv,
                   velocity_outlier=eps)
    mats = phd.matrices(1.0)
    g = torch.Generator().manual_seed(6)
    J, M = 3, 5
    state, mean, cov, w = _random_mixture(g, J, 2.0)
    z = torch.randn(M, 2, generator=g, dtype=F64) * 2
    v = torch.randn(M, 2, generator=g, dtype=F64) * 3
    post, info = phd.update(state, z, mats, velocity=v)
    zz = torch.cat([z, v], 1)
    s_z, s_v = phd.measurement.sigma().detach(), phd.velocity_sigma().detach()
    kv = phd.velocity_clutter_density().detach()                                   # float32-rounded 0.01
    R4 = torch.diag(torch.stack([s_z, s_z, s_v, s_v]).reshape(4) ** 2)
    g4, g2 = torch.zeros(J, M, dtype=F64), torch.zeros(J, M, dtype=F64)
    upd = torch.zeros(J, M, 4, dtype=F64)
    cov_upd = torch.zeros(J, M, 4, 4, dtype=F64)
    for j in range(J):
        S4, S2 = cov[j] + R4, cov[j][:2, :2] + R4[:2, :2]
        g4[j] = torch.distributions.MultivariateNormal(mean[j], S4).log_prob(zz).exp()
        g2[j] = torch.distributions.MultivariateNormal(mean[j][:2], S2).log_prob(z).exp()
        K4, K2 = cov[j] @ torch.linalg.inv(S4), cov[j][:, :2] @ torch.linalg.inv(S2)
        for k in range(M):
            with_v = (1 - eps) * g4[j, k] >= eps * kv * g2[j, k]
            upd[j, k] = mean[j] + (K4 @ (zz[k] - mean[j]) if with_v else K2 @ (z[k] - mean[j][:2]))
            cov_upd[j, k] = cov[j] - (K4 @ S4 @ K4.T if with_v else K2 @ S2 @ K2.T)
    pd = phd.p_detection().detach()
    num = pd * w[:, None] * ((1 - eps) * g4 + eps * kv * g2)
    clutter = phd.clutter_density().detach() * kv
    torch.testing.assert_close(post.log_weight[J:].exp().detach().reshape(J, M), num / (clutter + num.sum(0)),
                               rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(post.mean[J:].detach().reshape(J, M, 4), upd, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(post.cov[J:].detach().reshape(J, M, 4, 4), cov_upd, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(info.log_denominator.detach(), torch.log(clutter + num.sum(0)), rtol=1e-9, atol=1e-9)
    # one target at rest, detected where predicted but with a velocity 15 px/frame off
    target = one([0.0, 0.0, 0.0, 0.0], np.diag([1.0, 1.0, 0.5, 0.5]))
    z1, v1 = torch.tensor([[0.3, -0.2]], dtype=F64), torch.tensor([[15.0, 0.0]], dtype=F64)
    plain = make_phd(pd=0.8, kappa=2e-3, velocity_sigma=0.7, velocity_clutter_density=0.01)
    assert plain.update(target, z1, plain.matrices(1.0), velocity=v1)[0].size == 1      # gated out: missed only
    robust, _ = phd.update(target, z1, mats, velocity=v1)
    assert robust.size == 2 and robust.log_weight[1].exp() > 0.5
    assert abs(float(robust.mean[1, 2])) < 1.0                                           # the velocity is ignored
    with pytest.raises(TorchtrackError, match="velocity_outlier"):
        make_phd(velocity_sigma=0.7, velocity_outlier=1.0)


def test_gradients_reach_the_velocity_noise_and_velocity_clutter_density():
    tracker = GMPHDTracker(GMPHD(ConstantVelocity(2, q=0.5), LinearPosition(2, sigma=1.0),
                                 GMPHDFilterOptions(velocity_sigma=1.0)),
                           AdaptiveBirth(GMPHDBirthOptions(birth_weight=0.05)), GMPHDConfig(dtype="float64"))
    g = torch.Generator().manual_seed(1)
    p = torch.tensor([[20.0, 30.0], [60.0, 50.0]], dtype=F64)
    v = torch.tensor([[1.0, 0.5], [-0.5, 1.0]], dtype=F64)
    zs, vs = [], []
    for t in range(5):
        zs.append(torch.cat([p + v * t + 0.5 * torch.randn(2, 2, generator=g, dtype=F64),
                             torch.rand(2, 2, generator=g, dtype=F64) * 100]))
        vs.append(torch.cat([v + 0.3 * torch.randn(2, 2, generator=g, dtype=F64), torch.zeros(2, 2, dtype=F64)]))
    tracker.log_likelihood(zs, vs).sum().backward()
    for prm in (tracker.phd.velocity_sigma.raw, tracker.phd.velocity_clutter_density.raw,
                tracker.phd.p_detection.raw, tracker.phd.measurement.sigma.raw):
        assert prm.grad is not None and torch.isfinite(prm.grad).all() and prm.grad.abs().sum() > 0


def test_dense_and_screened_merges_agree(monkeypatch):
    """Small mixtures test every pair at once, large ones screen pairs on positions first: same merge."""
    import torchtrack.filters.gmphd.filter as gm

    g = torch.Generator().manual_seed(4)
    for _ in range(30):
        J = int(torch.randint(2, 80, (1,), generator=g))
        mean = torch.randn(J, 4, generator=g, dtype=F64) * float(torch.rand(1, generator=g) * 8 + 0.5)
        A = torch.randn(J, 4, 4, generator=g, dtype=F64) * 0.5
        cov = A @ A.transpose(-1, -2) + torch.eye(4, dtype=F64)
        state = MixtureState(torch.rand(J, generator=g, dtype=F64).log(), mean, cov, torch.arange(J),
                             torch.ones(J, dtype=torch.bool))
        monkeypatch.setattr(gm, "DENSE_MERGE", 256)
        dense = merge(state, 9.0, 3, keep_label=torch.tensor([J - 1]))
        monkeypatch.setattr(gm, "DENSE_MERGE", 0)
        screened = merge(state, 9.0, 3, keep_label=torch.tensor([J - 1]))
        assert dense.size == screened.size
        assert torch.equal(dense.label, screened.label)
        for a, b in zip(dense[:3], screened[:3]):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
