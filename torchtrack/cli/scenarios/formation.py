"""``torchtrack scenario formation``: the options, Table 1, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.formation`."""

import math

from torchtrack.cli.scenarios import run_scenario
from torchtrack.scenarios import formation

NAME = "formation"
HELP = "class-conditioned tracking gates on the ground formation (the gate paper, Table 1)"
DESCRIPTION = formation.__doc__
DEFAULT_CONFIG = formation.DEFAULT_CONFIG
RUNS = 100
PARAMS = "every class IMM's transition matrix and process and measurement noise (an 'imm' file with 3 modes)"
"""What a fitted-parameter file (``--params``) sets in this scenario."""


def run(args) -> int:
    report = run_scenario(args, NAME, formation,
                          lambda: formation.run_gates(args.config, args.runs, args.seed, args.params))
    return 0 if all(math.isfinite(v) for v in report.gate_volume.values()) else 1
