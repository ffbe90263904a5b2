"""``torchtrack scenario maneuver``: the options, the printed tables, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.maneuver`."""

from torchtrack.cli.scenarios import run_scenario
from torchtrack.scenarios import maneuver

NAME = "maneuver"
HELP = "Kalman refinement and chi-square maneuver detection (the maneuver paper)"
DESCRIPTION = maneuver.__doc__
DEFAULT_CONFIG = maneuver.DEFAULT_CONFIG
RUNS = 100
PARAMS = ("the Kalman filter's q and sigma of the constant-velocity and maneuver experiments (a 'kalman' file, "
          "motion cv, noise pwca)")
"""What a fitted-parameter file (``--params``) sets in this scenario."""


def run(args) -> int:
    run_scenario(args, NAME, maneuver, lambda: maneuver.run_experiments(args.config, args.runs, args.seed, args.params))
    return 0
