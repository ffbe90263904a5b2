"""Tuning a Kalman filter: likelihood gradient vs finite differences, recovery, trainer safeguards."""

import math

import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.tuning.parameters import get_raw, set_raw, tunable_parameters
from torchtrack.tuning.registry import TuneData
from torchtrack.tuning.tune import fit, get_tunable, get_values, select_trainable


def small_problem(q=1.0, sigma=2.0, sequences=6, steps=30, seed=0, **model):
    tun = get_tunable("kalman", {"q": 3.0 * q, "sigma": 3.0 * sigma, "dtype": "float64", **model})
    data = tun.load_data({"simulate": {"sequences": sequences, "steps": steps, "q": q, "sigma": sigma},
                          "held_out": 2}, torch.Generator().manual_seed(seed))
    return tun, tun.build(), data


def test_named_parameters_are_dotted_module_paths():
    tun, kf, _ = small_problem()
    assert set(tunable_parameters(kf)) == {"motion.q", "measurement.sigma"}
    values = get_values(kf)
    assert values["motion.q"].item() == pytest.approx(3.0)
    assert values["measurement.sigma"].item() == pytest.approx(6.0)


@pytest.mark.parametrize("loss", ["nll", "gospa"])
def test_loss_gradient_matches_finite_differences(loss):
    tun, kf, data = small_problem(sequences=3, steps=12)
    select_trainable(kf, ["motion.q", "measurement.sigma"])
    value = tun.loss(kf, data.train, loss)
    value.backward()
    params = tunable_parameters(kf)
    h = 1e-6
    for name, p in params.items():
        grad = p.raw.grad.item()
        base = get_raw(kf)
        vals = []
        for sign in (1, -1):
            shifted = dict(base)
            shifted[name] = base[name] + sign * h
            set_raw(kf, shifted)
            with torch.no_grad():
                vals.append(tun.loss(kf, data.train, loss).item())
        set_raw(kf, base)
        fd = (vals[0] - vals[1]) / (2 * h)
        assert grad == pytest.approx(fd, rel=1e-5, abs=1e-8), name


def test_likelihood_matches_dense_gaussian_marginal():
    """The loss is −log p(z_1:T | z_0) of the joint Gaussian of the measurements (brute force)."""
    tun, kf, data = small_problem(sequences=3, steps=6)
    track = data.train[0]
    n_meas = 5  # measurement vectors after z_0
    with torch.no_grad():
        nll = tun.loss(kf, [track], "nll").item() * n_meas
        F = kf.motion.transition_matrix(1.0)
        Q = kf.motion.process_noise(1.0)
        R = kf.measurement.noise_cov()
        H = kf.measurement.matrix()
        x0 = tun.initial_state(kf, track.z[:1])
        # stack x_1..x_5 = F^k x0 + Σ F^(k-j) w_j; z_k = H x_k + v_k
        T = 5
        mean = []
        Fp = [torch.linalg.matrix_power(F, k) for k in range(T + 1)]
        covx = {}
        for i in range(1, T + 1):
            mean.append(H @ Fp[i] @ x0.mean[0])
            for j in range(1, T + 1):
                lo = min(i, j)
                c = Fp[i] @ x0.cov[0] @ Fp[j].T
                for k in range(1, lo + 1):
                    c = c + Fp[i - k] @ Q @ Fp[j - k].T
                covx[i, j] = c
        S = torch.cat([torch.cat([H @ covx[i, j] @ H.T + (R if i == j else 0 * R) for j in range(1, T + 1)], 1)
                       for i in range(1, T + 1)], 0)
        z = track.z[1:T + 1].reshape(-1)
        ref = -torch.distributions.MultivariateNormal(torch.cat(mean), S).log_prob(z).item()
    assert nll == pytest.approx(ref, rel=1e-9)


def test_fit_moves_parameters_towards_the_truth():
    tun, kf, data = small_problem(sequences=8, steps=40)
    res = fit(tun, kf, ["motion.q", "measurement.sigma"], data, "nll",
              {"name": "lbfgs", "steps": 3, "max_iter": 10}, {"patience": 10}, progress=False)
    truth = {"motion.q": 1.0, "measurement.sigma": 2.0}
    for name, t in truth.items():
        start, final = res.start[name].item(), res.final[name].item()
        assert abs(math.log(final / t)) < 0.5 * abs(math.log(start / t)), (name, start, final)
    assert res.held_out and res.evaluations > 0


def test_adam_minibatches_and_only_selected_parameters_move():
    tun, kf, data = small_problem(sequences=8, steps=20)
    sigma0 = get_values(kf)["measurement.sigma"].clone()
    res = fit(tun, kf, ["motion.q"], data, "nll", {"name": "adam", "lr": 0.1, "steps": 12, "batch_size": 2},
              {"patience": 100}, progress=False)
    assert len(res.train_loss) == 12
    assert torch.equal(get_values(kf)["measurement.sigma"], sigma0)
    assert res.final["motion.q"].item() < 3.0
    assert not tunable_parameters(kf)["measurement.sigma"].raw.requires_grad


def test_unknown_parameter_name_lists_the_valid_names():
    tun, kf, data = small_problem()
    with pytest.raises(TorchtrackError, match=r"'motion\.qq'.*valid names: measurement\.sigma, motion\.q"):
        select_trainable(kf, ["motion.qq"])
    with pytest.raises(TorchtrackError, match="valid names"):
        fit(tun, kf, ["sigma"], data, progress=False)


def test_empty_training_set_is_an_error(tmp_path):
    tun, kf, _ = small_problem()
    with pytest.raises(TorchtrackError, match="training set is empty"):
        fit(tun, kf, ["motion.q"], TuneData([], []), progress=False)
    empty = tmp_path / "empty.txt"
    empty.write_text("")
    with pytest.raises(TorchtrackError, match="no track"):
        tun.load_data({"file": str(empty)}, torch.Generator())
    _, _, data = small_problem()
    with pytest.raises(TorchtrackError, match="leaves no training data"):
        tun.load_data({"simulate": {"sequences": 2, "steps": 5}, "held_out": 2}, torch.Generator())
    assert data.train


class FailingKalman(type(get_tunable("kalman"))):
    """A Kalman tunable whose loss turns NaN at the ``fail_at``-th call; records parameters per call."""

    def __init__(self, options, fail_at):
        super().__init__(options)
        self.fail_at, self.calls, self.seen = fail_at, 0, []

    def loss(self, module, items, loss):
        self.calls += 1
        self.seen.append(get_raw(module))
        value = super().loss(module, items, loss)
        return value * float("nan") if self.calls >= self.fail_at else value


def test_non_finite_loss_stops_and_keeps_the_last_good_parameters():
    _, _, data = small_problem()
    tun = FailingKalman({"q": 3.0, "sigma": 6.0, "dtype": "float64"}, fail_at=4)
    kf = tun.build()
    res = fit(tun, kf, ["motion.q", "measurement.sigma"], TuneData(data.train, []), "nll",
              {"name": "adam", "lr": 0.1, "steps": 50, "batch_size": 4}, progress=False)
    assert res.stopped == "non-finite"
    assert "stopped at step 4" in res.message and "nan" in res.message.lower()
    assert len(res.train_loss) == 3
    final = get_raw(kf)
    for name, value in tun.seen[2].items():   # parameters of the last finite evaluation (call 3)
        assert torch.equal(final[name], value)
    assert all(torch.isfinite(v).all() for v in get_values(kf).values())


def test_recorded_tracks_from_a_mot_file_with_gaps(tmp_path):
    from torchtrack.io.mot import from_points, write_motdata

    frames = [1, 2, 3, 5, 6, 2, 3, 4, 5, 6, 7]
    ids = [1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2]
    xs = [10.0, 11.0, 12.5, 14.0, 15.0, 50.0, 49.0, 48.0, 47.5, 46.0, 45.0]
    path = tmp_path / "tracks.txt"
    write_motdata(path, from_points(frames, ids, xs, [5.0] * len(xs)))
    tun = get_tunable("kalman", {"q": 1.0, "sigma": 1.0})
    data = tun.load_data({"file": str(path)}, torch.Generator())
    assert [t.z.shape[0] for t in data.train] == [6, 6]
    assert bool(torch.isnan(data.train[0].z[3]).all())          # frame 4 of id 1 is missing
    assert data.train[1].z[0].tolist() == pytest.approx([50.0, 5.0])
    kf = tun.build()
    assert torch.isfinite(tun.loss(kf, data.train, "nll"))
    with pytest.raises(TorchtrackError, match="needs truth"):
        tun.loss(kf, data.train, "gospa")
