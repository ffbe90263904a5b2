"""``torchtrack scenario maneuver``: the options, the printed tables, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.maneuver`."""

from torchtrack.cli.scenarios import check_runs, plot_folder
from torchtrack.io.outputs import write_json
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
    check_runs(args.runs)
    with plot_folder(args, NAME) as plots:
        report = maneuver.run_experiments(args.config, args.runs, args.seed, args.params)
        print(maneuver.format_report(report))
        write_json(args.json, maneuver.report_json(report))
        if plots is not None:
            from torchtrack.scenarios._maneuver_plots import plot_all

            paths = plot_all(plots, report.stationary, report.constant_velocity, report.maneuver, report.config)
    if args.plot is not None:
        print("\nplots: " + ", ".join(str(args.plot / p.name) for p in paths))
    return 0
