"""
Fitting the measurement noise by gradient
=========================================

Every filter is differentiable: the Kalman filter's log-likelihood of the measurements is maximised over the
measurement noise ``sigma`` and the process noise ``q`` with Adam. Data simulated with ``sigma = 2`` and
``q = 0.1``; the fit starts from ``sigma = 0.5``, ``q = 1``.
"""

import matplotlib.pyplot as plt
import torch

from torchtrack.filters.kalman import GaussianState, KalmanFilter
from torchtrack.models import ConstantVelocity, LinearPosition

torch.manual_seed(1)
T, B = 60, 200
truth_model = KalmanFilter(ConstantVelocity(ndim=2, q=0.1), LinearPosition(ndim=2, sigma=2.0)).double()
with torch.no_grad():
    F = truth_model.motion.transition_matrix(1.0)
    chol_q = torch.linalg.cholesky(truth_model.motion.process_noise(1.0))
x = torch.zeros(B, 4, dtype=torch.float64)
zs = []
for _ in range(T):
    x = x @ F.T + torch.randn(B, 4, dtype=torch.float64) @ chol_q.T
    zs.append(x[:, :2] + 2.0 * torch.randn(B, 2, dtype=torch.float64))
z = torch.stack(zs)

kf = KalmanFilter(ConstantVelocity(ndim=2, q=1.0), LinearPosition(ndim=2, sigma=0.5)).double()
init = GaussianState(torch.zeros(B, 4, dtype=torch.float64), 10 * torch.eye(4, dtype=torch.float64).expand(B, 4, 4))
optimiser = torch.optim.Adam(kf.parameters(), lr=0.1)
history = []
for _ in range(300):
    optimiser.zero_grad()
    loss = -kf.run(z, init, history=False).log_likelihood.mean() / T
    loss.backward()
    optimiser.step()
    with torch.no_grad():
        history.append((float(kf.measurement.sigma()), float(kf.motion.q())))

sigma, q = history[-1]
print(f"fitted sigma {sigma:.3f} (true 2), q {q:.3f} (true 0.1)")

fig, ax = plt.subplots(figsize=(5, 3.5))
ax.plot([h[0] for h in history], label="sigma")
ax.plot([h[1] for h in history], label="q")
ax.axhline(2.0, color="C0", ls=":")
ax.axhline(0.1, color="C1", ls=":")
ax.set_xlabel("Adam step")
ax.legend()
fig.tight_layout()
