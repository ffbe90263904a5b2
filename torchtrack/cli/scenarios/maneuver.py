"""``torchtrack scenario maneuver``: the options, the printed tables, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.maneuver`."""

from torchtrack.cli.scenarios import run_scenario
from torchtrack.scenarios import maneuver

NAME = "maneuver"
HELP = "Kalman refinement and chi-square maneuver detection (the maneuver paper)"
DESCRIPTION = """The maneuver paper's three experiments, all Monte Carlo runs batched:

1. refinement of a stationary target's latitude and longitude (section 3.1, Fig. 1-2);
2. a constant-velocity target (section 3.2, Fig. 3-7);
3. a target maneuvering at scans 60 and 125, tracked by a plain Kalman filter and by the filter with
   chi-square maneuver detection and reset (sections 3.3 and 4.1, Fig. 8-9).

Example: torchtrack scenario maneuver --runs 100 --plot out/maneuver
"""
DEFAULT_CONFIG = maneuver.DEFAULT_CONFIG
RUNS = 100
PARAMS = ("the Kalman filter's q and sigma of the constant-velocity and maneuver experiments (a 'kalman' file, "
          "motion cv, noise pwca)")
"""What a fitted-parameter file (``--params``) sets in this scenario."""


def run(args) -> int:
    run_scenario(args, NAME, maneuver, lambda: maneuver.run_experiments(args.config, args.runs, args.seed, args.params))
    return 0
