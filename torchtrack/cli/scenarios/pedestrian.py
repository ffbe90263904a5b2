"""``torchtrack scenario pedestrian``: the options, the OSPA table, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.pedestrian`."""

import argparse

from torchtrack.cli.scenarios import run_scenario
from torchtrack.scenarios import pedestrian

NAME = "pedestrian"
HELP = "feature tracking with an uncertain sensor position: joint filter vs variance inflation vs naive (PMB paper)"
DESCRIPTION = """The PMB paper's experiment (section 5): feature tracking from a vehicle whose own position is
uncertain.

A simulated counterpart of the paper's recording: a vehicle standing still, a static feature at about 50 m,
a pedestrian who enters at step 208, walks away, rests at about 10, 20 and 30 m and leaves at step 1330;
0.1 s steps, 1461 steps; GNSS fixes of the vehicle, relative measurements of the features, p_D 0.9, 10
false alarms per scan.

Three TOMB/P filters track the features from the same data: naive (the sensor is where the GNSS fix says),
inflated (the measurement noise increased by the GNSS covariance) and joint (the joint vehicle-feature
filter). Printed: each one's OSPA (c = 20 m, p = 2) averaged over steps and runs (the paper: 0.87, 0.99,
2.61).

Example: torchtrack scenario pedestrian --runs 2 --steps 300
"""
DEFAULT_CONFIG = pedestrian.DEFAULT_CONFIG
RUNS = 10
PROGRESS = True


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--steps", type=int, default=None, help="shorten the recording to this many steps")
    parser.add_argument("--p-survival", type=float, default=None,
                        help="feature survival probability (config default 0.99; the paper states 0.7)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: the tensors are small, more threads only spin)")


def run(args) -> int:
    run_scenario(args, NAME, pedestrian, lambda: pedestrian.run_variants(
        args.config, args.runs, args.seed, steps=args.steps, p_survival=args.p_survival, threads=args.threads,
        progress=not args.no_progress))
    return 0
