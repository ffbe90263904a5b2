"""``torchtrack scenario pedestrian``: the options, the OSPA table, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.pedestrian`."""

import argparse

from torchtrack.cli.scenarios import run_scenario
from torchtrack.scenarios import pedestrian

NAME = "pedestrian"
HELP = "feature tracking with an uncertain sensor position: joint filter vs variance inflation vs naive (PMB paper)"
DESCRIPTION = pedestrian.__doc__
DEFAULT_CONFIG = pedestrian.DEFAULT_CONFIG
RUNS = 10


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--steps", type=int, default=None, help="shorten the recording to this many steps")
    parser.add_argument("--p-survival", type=float, default=None,
                        help="feature survival probability (config default 0.99; the paper states 0.7)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: the tensors are small, more threads only spin)")


def run(args) -> int:
    run_scenario(args, NAME, pedestrian, lambda: pedestrian.run_variants(
        args.config, args.runs, args.seed, steps=args.steps, p_survival=args.p_survival, threads=args.threads))
    return 0
