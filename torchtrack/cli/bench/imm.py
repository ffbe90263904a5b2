"""``torchtrack bench imm``: the options and the output of :mod:`torchtrack.bench.imm`."""

import argparse

from torchtrack.bench import imm
from torchtrack.cli._common import positive_int
from torchtrack.cli.bench import add_threads_option, report

NAME = "imm"
HELP = "3-model IMM, 100 000 tracks, against FilterPy's IMMEstimator per track"
DESCRIPTION = """A 3-model IMM on [x, y, vx, vy] for many tracks at once against FilterPy's IMMEstimator run one
track at a time, timed in the same run.

Each step is a full IMM cycle: interaction, three model-matched predictions and updates, mode update and
combination; torchtrack runs all tracks in one batch (compiled with torch.compile unless --no-compile).
Rates are track-steps per second, per wall-clock second and per CPU second of this process. FilterPy is a
test-only dependency (pip install torchtrack-mtt[test]).

Example: torchtrack bench imm --tracks 10000 --steps 20
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tracks", type=positive_int, default=100_000, help="tracks filtered at once (default 100000)")
    parser.add_argument("--steps", type=positive_int, default=20, help="time steps per timed pass (default 20)")
    parser.add_argument("--reference-tracks", type=positive_int, default=100,
                        help="tracks run through FilterPy (default 100)")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32",
                        help="floating-point type of both implementations")
    add_threads_option(parser)
    parser.add_argument("--no-compile", action="store_true", help="eager step instead of torch.compile")


def run(args) -> int:
    result = imm.measure(args.tracks, args.steps, args.reference_tracks, args.dtype, args.threads,
                         not args.no_compile, args.seed)
    return report(args, result, imm.format_report(result, min(args.reference_tracks, args.tracks)))
