"""``torchtrack scenario pedestrian``: the options, the OSPA table, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.pedestrian`."""

import argparse

from torchtrack.cli.scenarios import check_runs, plot_folder
from torchtrack.io.outputs import write_json
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
    check_runs(args.runs)
    with plot_folder(args, NAME) as plots:
        report = pedestrian.run_variants(args.config, args.runs, args.seed, steps=args.steps,
                                         p_survival=args.p_survival, threads=args.threads)
        print(pedestrian.format_report(report))
        write_json(args.json, pedestrian.report_json(report))
        if plots is not None:
            from torchtrack.scenarios._pedestrian_plots import plot_all

            plot_all(plots, report.truth, report.variants,
                     {v: report.ospa_per_step[v] for v in pedestrian.VARIANTS}, report.mean_ospa)
    if args.plot is not None:
        print(f"figures written to {args.plot}")
    return 0
