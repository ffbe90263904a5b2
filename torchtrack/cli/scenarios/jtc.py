"""``torchtrack scenario jtc``: the options, the printed table, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.jtc`."""

import argparse

from torchtrack.cli._common import positive_int
from torchtrack.cli.scenarios import run_scenario
from torchtrack.scenarios import jtc

NAME = "jtc"
HELP = "joint tracking and classification with a bank of multiple-model particle filters (the JTC paper)"
DESCRIPTION = """The JTC paper's experiment (Angelova, Mihaylova & Semerdjiev, section 4): joint tracking and
classification of a maneuvering aircraft.

A bank of two class-dependent multiple-model particle filters (commercial and military aircraft, 3000
particles each) tracks and classifies a class-2 target from range-bearing radar measurements, with and
without the speed likelihoods; all Monte Carlo runs are one batch. Printed per scan (mean over runs): the
probability of the true class, the position and speed RMSE, the probability of the correct motion mode, and
the time per update.

Example: torchtrack scenario jtc --runs 10 --plot out/jtc
"""
DEFAULT_CONFIG = jtc.DEFAULT_CONFIG
RUNS = 100
PROGRESS = True


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-speed-constraints", action="store_true",
                        help="report the bank without speed likelihoods as the main result")
    parser.add_argument("--particles", type=int, default=None,
                        help="particles per class (default: the config's, 3000 as in the paper)")
    parser.add_argument("--threads", type=positive_int, default=1,
                        help="torch intra-op threads (default 1: a 6000-particle step is too small to share, "
                             "and on a loaded machine spinning threads cost more than they give)")
    parser.add_argument("--timing-repeats", type=int, default=5,
                        help="one-run passes over the trajectory for the time per update; the best pass's "
                             "median is reported (default 5)")
    parser.add_argument("--compile", action="store_true",
                        help="torch.compile the filter step (inductor; needs a C compiler; ~1 min of compilation "
                             "per batch shape, then ~25%% less CPU per scan)")


def run(args) -> int:
    run_scenario(args, NAME, jtc, lambda: jtc.run_jtc(
        args.config, args.runs, args.seed, speed_constraints=not args.no_speed_constraints, particles=args.particles,
        threads=args.threads, timing_repeats=args.timing_repeats, compile_step=args.compile,
        progress=not args.no_progress))
    return 0
