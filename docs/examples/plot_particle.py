"""
A bootstrap particle filter against the Kalman filter
=====================================================

On a linear-Gaussian model the Kalman filter is exact, so a particle filter's estimate must approach it as
the particles grow; 100 Monte Carlo runs are filtered in one call for each particle count.
"""

import matplotlib.pyplot as plt
import torch

from torchtrack.filters.kalman import GaussianState, KalmanFilter
from torchtrack.filters.particle import ParticleFilter
from torchtrack.models import ConstantVelocity, LinearPosition

torch.manual_seed(2)
T, RUNS = 30, 100
motion, measurement = ConstantVelocity(ndim=1, q=0.1), LinearPosition(ndim=1, sigma=1.0)
kf = KalmanFilter(motion, measurement).double()
position = torch.randn(RUNS, dtype=torch.float64) + (0.5 * torch.arange(1, T + 1, dtype=torch.float64))[:, None]
z = (position + torch.randn(T, RUNS, dtype=torch.float64))[..., None]
init = GaussianState(torch.zeros(RUNS, 2, dtype=torch.float64),
                     4 * torch.eye(2, dtype=torch.float64).expand(RUNS, 2, 2))
with torch.no_grad():
    exact = kf.run(z, init).mean[..., 0]

counts, gaps = [32, 128, 512, 2048], []
for n in counts:
    pf = ParticleFilter(motion, measurement, num_particles=n).double()
    with torch.no_grad():
        run = pf.run(z, init.mean, init.cov, 1.0, generator=torch.Generator().manual_seed(n))
    gaps.append(float((run.mean[..., 0] - exact).abs().mean()))
    print(f"{n:5d} particles: mean |particle - Kalman| = {gaps[-1]:.4f}")

fig, ax = plt.subplots(figsize=(5, 3.5))
ax.loglog(counts, gaps, "o-")
ax.set_xlabel("particles")
ax.set_ylabel("mean distance to the Kalman filter")
fig.tight_layout()
