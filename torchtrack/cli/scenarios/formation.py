"""``torchtrack scenario formation``: the options, Table 1, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.formation`."""

import math

from torchtrack.cli.scenarios import run_scenario
from torchtrack.scenarios import formation

NAME = "formation"
HELP = "class-conditioned tracking gates on the ground formation (the gate paper, Table 1)"
DESCRIPTION = """The gate paper's ground-formation experiment (section 5, Table 1): class-conditioned tracking gates.

Four targets (classes 1, 2, 1, 2) move left to right 200 m apart; every track runs a class-conditioned IMM
bank and measurements are associated by global nearest neighbour over the pairs that a gate admits. The
gates compared: rectangular, ellipsoidal, and class-conditioned (the classifier's report joined with the
track's class-conditioned Gaussian mixture through the confusion matrix), the last as the moment-matched
ellipse and as the exact highest-density region found by sampling (the config's cc_region picks the one in
the table's class_conditioned row).

Printed: the probability that a detected target's measurement is associated with its own track, per class
and gate (the paper's Table 1), and each gate's mean area; with --plot, the estimated trajectories per gate.

Example: torchtrack scenario formation --runs 20 --plot out/formation
"""
DEFAULT_CONFIG = formation.DEFAULT_CONFIG
RUNS = 100
PROGRESS = True
PARAMS = "every class IMM's transition matrix and process and measurement noise (an 'imm' file with 3 modes)"
"""What a fitted-parameter file (``--params``) sets in this scenario."""


def run(args) -> int:
    report = run_scenario(args, NAME, formation,
                          lambda: formation.run_gates(args.config, args.runs, args.seed, args.params,
                                                      progress=not args.no_progress))
    return 0 if all(math.isfinite(v) for v in report.gate_volume.values()) else 1
