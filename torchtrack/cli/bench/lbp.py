"""``torchtrack bench lbp``: its command half still lives in :mod:`torchtrack.bench.lbp` (issue #24: moves here
once the kernel work on that module has landed)."""

from torchtrack.bench import lbp

NAME = "lbp"
HELP = "LBP association marginals on n x n problems against a NumPy implementation"
DESCRIPTION = lbp.DESCRIPTION
add_arguments = lbp.add_arguments
run = lbp.run
