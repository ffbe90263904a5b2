"""The filters and trackers on a CUDA device give what they give on the CPU (skipped where no GPU is present).

Each test runs the same computation on the CPU and on ``cuda``, float64, and asserts the results agree and that
the outputs stay on the device (nothing silently moved to the host).
"""

import numpy as np
import pytest
import torch

from torchtrack.filters.trackers.protocol import make_tracker

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (runs where a GPU exists)")]


def scene(frames=25, targets=40, clutter=15, seed=0):
    """Straight-line targets with noisy detections, clutter and detector velocities, as float64 tensors."""
    rng = np.random.default_rng(seed)
    start, vel = rng.uniform(50, 450, (targets, 2)), rng.normal(0, 2, (targets, 2))
    out = []
    for f in range(1, frames + 1):
        z = np.vstack([start + f * vel + rng.normal(0, 0.5, (targets, 2)), rng.uniform(0, 500, (clutter, 2))])
        v = np.vstack([vel + rng.normal(0, 0.3, (targets, 2)), rng.normal(0, 1, (clutter, 2))])
        out.append((f, torch.as_tensor(z), torch.as_tensor(v)))
    return out


TRACKER_CONFIGS = {"gmphd": {"dtype": "float64"}, "labelled-gmphd": {"dtype": "float64"}, "sort": None,
                   "greedy": None, "pmb": None, "glmb": None}


@pytest.mark.parametrize("name", list(TRACKER_CONFIGS))
def test_tracker_on_cuda_equals_cpu(name):
    runs = {}
    for device in ("cpu", "cuda"):
        tracker = make_tracker(name, TRACKER_CONFIGS[name])
        tracker.reset()
        outputs = []
        for f, z, v in scene():
            ids, pos = tracker.step(f, z.to(device), v.to(device))
            assert ids.device.type == device and pos.device.type == device
            outputs.append((ids.cpu(), pos.cpu()))
        runs[device] = outputs
    for (ids_cpu, pos_cpu), (ids_gpu, pos_gpu) in zip(runs["cpu"], runs["cuda"]):
        assert torch.equal(ids_cpu, ids_gpu)
        torch.testing.assert_close(pos_gpu, pos_cpu, rtol=0, atol=1e-6)


def test_kalman_filter_run_on_cuda_equals_cpu():
    from torchtrack.filters.kalman.filter import GaussianState, KalmanFilter
    from torchtrack.models import ConstantVelocity, LinearPosition

    z = torch.randn(30, 500, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).cumsum(0)
    z[5, :10] = float("nan")  # missing measurements
    results = {}
    for device in ("cpu", "cuda"):
        kf = KalmanFilter(ConstantVelocity(ndim=2, q=0.1), LinearPosition(ndim=2, sigma=1.0)).double().to(device)
        init = GaussianState(torch.zeros(500, 4, dtype=torch.float64, device=device),
                             torch.eye(4, dtype=torch.float64, device=device) * 10)
        res = kf.run(z.to(device), init)
        assert res.mean.device.type == device
        results[device] = res
    torch.testing.assert_close(results["cuda"].mean.cpu(), results["cpu"].mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(results["cuda"].log_likelihood.cpu(), results["cpu"].log_likelihood,
                               rtol=1e-10, atol=1e-10)


def test_lbp_marginals_on_cuda_equal_cpu():
    from torchtrack.association.lbp import lbp_marginals

    g = torch.Generator().manual_seed(2)
    log_w = torch.randn(8, 30, 40, dtype=torch.float64, generator=g) * 3
    log_w[torch.rand(8, 30, 40, generator=g) < 0.6] = float("-inf")  # pairs outside the gate
    log_miss = torch.randn(8, 30, dtype=torch.float64, generator=g)
    log_new = torch.randn(8, 40, dtype=torch.float64, generator=g)
    cpu = lbp_marginals(log_w, log_miss, log_new)
    gpu = lbp_marginals(log_w.cuda(), log_miss.cuda(), log_new.cuda())
    for a, b in zip(cpu, gpu):
        if isinstance(a, torch.Tensor):
            assert b.device.type == "cuda"
            torch.testing.assert_close(b.cpu(), a, rtol=1e-9, atol=1e-12)


def test_track_command_on_cuda_writes_the_cpu_tracks(tmp_path):
    from torchtrack.cli import main
    from torchtrack.io.mot import from_points, read_mot, write_motdata

    frames = scene(frames=15, targets=20, clutter=5)
    f = np.concatenate([np.full(len(z), k) for k, z, _ in frames])
    xy = np.concatenate([z.numpy() for _, z, _ in frames])
    write_motdata(tmp_path / "det.txt", from_points(f, -np.ones(len(f), int), xy[:, 0], xy[:, 1]))
    for device in ("cpu", "cuda"):
        assert main(["track", "--detections", str(tmp_path / "det.txt"), "--device", device,
                     "--out", str(tmp_path / device)]) == 0
    cpu, gpu = read_mot(tmp_path / "cpu" / "tracks.txt"), read_mot(tmp_path / "cuda" / "tracks.txt")
    assert np.array_equal(cpu.id, gpu.id) and np.allclose(cpu.x, gpu.x, atol=1e-3)
