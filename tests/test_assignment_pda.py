"""PDA update against the moment match of its hypothesis mixture, and its Kalman limit."""

import math

import torch

from torchtrack.association.pda import pda_update
from torchtrack.filters.kalman.filter import GaussianState
from torchtrack.gaussian import kalman_update, log_prob, moment_match

F64 = torch.float64


def _setup(seed=0):
    g = torch.Generator().manual_seed(seed)
    T, Mz = 3, 5
    x = torch.randn(T, 4, generator=g, dtype=F64) * 5
    A = torch.randn(T, 4, 4, generator=g, dtype=F64)
    P = A @ A.transpose(-1, -2) + torch.eye(4, dtype=F64)
    H = torch.zeros(2, 4, dtype=F64)
    H[0, 0] = H[1, 1] = 1.0
    R = torch.diag(torch.tensor([1.0, 2.0], dtype=F64))
    z = torch.randn(Mz, 2, generator=g, dtype=F64) * 5
    mask = torch.rand(T, Mz, generator=g) < 0.7
    return GaussianState(x, P), z, mask, H, R


def test_pda_equals_moment_matched_hypothesis_mixture():
    state, z, mask, H, R = _setup()
    pd, pg, lam = 0.9, 0.99, 0.01
    res = pda_update(state, z, mask, H, R, pd, lam, pg)
    for t in range(state.mean.shape[0]):
        S = H @ state.cov[t] @ H.T + R
        logw, means, covs = [math.log(1 - pd * pg)], [state.mean[t]], [state.cov[t]]
        for j in range(z.shape[0]):
            if not mask[t, j]:
                continue
            up = kalman_update(state.mean[t], state.cov[t], z[j], H, R)
            logw.append(math.log(pd / lam) + float(log_prob(z[j], H @ state.mean[t], S)))
            means.append(up.mean)
            covs.append(up.cov)
        m, P = moment_match(torch.tensor(logw, dtype=F64), torch.stack(means), torch.stack(covs))
        torch.testing.assert_close(res.state.mean[t], m)
        torch.testing.assert_close(res.state.cov[t], P)
        w = torch.softmax(torch.tensor(logw, dtype=F64), 0)
        torch.testing.assert_close(res.weights[t, 0], w[0])
        torch.testing.assert_close(res.weights[t, 1:][mask[t]], w[1:])
        assert (res.weights[t, 1:][~mask[t]] == 0).all()


def test_pda_single_sure_measurement_is_the_kalman_update():
    state, z, _, H, R = _setup(1)
    mask = torch.zeros(3, 5, dtype=torch.bool)
    mask[:, 2] = True
    res = pda_update(state, z, mask, H, R, p_detect=1.0, clutter_density=1e-3, p_gate=1.0)
    up = kalman_update(state.mean, state.cov, z[2].expand(3, 2), H, R)
    torch.testing.assert_close(res.state.mean, up.mean)
    torch.testing.assert_close(res.state.cov, up.cov)
    assert torch.allclose(res.weights[:, 3], torch.ones(3, dtype=F64))
