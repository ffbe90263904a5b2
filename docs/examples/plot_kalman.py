"""
A Kalman filter on 1,000 tracks at once
=======================================

A nearly-constant-velocity Kalman filter follows 1,000 simulated targets in one tensor call; the plot shows
one target's truth, measurements and estimate, and the printed line the filter's consistency (the mean
normalised innovation squared is 2 for 2-D measurements when the model is right).
"""

import matplotlib.pyplot as plt
import torch

from torchtrack.filters.kalman import GaussianState, KalmanFilter
from torchtrack.models import ConstantVelocity, LinearPosition

torch.manual_seed(0)
T, B = 50, 1000
kf = KalmanFilter(ConstantVelocity(ndim=2, q=0.05), LinearPosition(ndim=2, sigma=1.0)).double()

# truth: constant velocity with small random accelerations; measurements: positions with unit noise
velocity = torch.randn(B, 2, dtype=torch.float64)
accel = 0.2 * torch.randn(T, B, 2, dtype=torch.float64)
velocity_t = velocity + accel.cumsum(0)
position = velocity_t.cumsum(0)
z = position + torch.randn(T, B, 2, dtype=torch.float64)

init = GaussianState(torch.zeros(B, 4, dtype=torch.float64), torch.diag(torch.tensor([1.0, 1, 4, 4])).double()
                     .expand(B, 4, 4))
with torch.no_grad():
    result = kf.run(z, init)

rmse_measured = (z - position).square().sum(-1).mean().sqrt()
rmse_filtered = (result.mean[..., :2] - position).square().sum(-1).mean().sqrt()
print(f"position RMSE: measurements {rmse_measured:.3f}, filtered {rmse_filtered:.3f}; "
      f"mean NIS {result.nis.mean():.2f} (2 expected)")

fig, ax = plt.subplots(figsize=(5, 4))
ax.plot(position[:, 0, 0], position[:, 0, 1], "k-", label="truth")
ax.plot(z[:, 0, 0], z[:, 0, 1], ".", color="0.6", label="measurements")
ax.plot(result.mean[:, 0, 0], result.mean[:, 0, 1], "C0-", label="Kalman filter")
ax.set_xlabel("x")
ax.set_ylabel("y")
ax.legend()
fig.tight_layout()
