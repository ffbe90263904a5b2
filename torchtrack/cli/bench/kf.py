"""``torchtrack bench kf``: its command half still lives in :mod:`torchtrack.bench.kf` (issue #24: moves here
once the kernel work on that module has landed)."""

from torchtrack.bench import kf

NAME = "kf"
HELP = "batched Kalman filter throughput vs NumPy and a per-track loop"
DESCRIPTION = kf.DESCRIPTION
add_arguments = kf.add_arguments
run = kf.run
