"""``torchtrack scenario formation``: the options, Table 1, ``--json`` and ``--plot`` of
:mod:`torchtrack.scenarios.formation`."""

import math

from torchtrack.cli.scenarios import check_runs, plot_folder
from torchtrack.io.outputs import write_json
from torchtrack.scenarios import formation

NAME = "formation"
HELP = "class-conditioned tracking gates on the ground formation (the gate paper, Table 1)"
DESCRIPTION = formation.__doc__
DEFAULT_CONFIG = formation.DEFAULT_CONFIG
RUNS = 100
PARAMS = "every class IMM's transition matrix and process and measurement noise (an 'imm' file with 3 modes)"
"""What a fitted-parameter file (``--params``) sets in this scenario."""


def run(args) -> int:
    check_runs(args.runs)
    with plot_folder(args, NAME) as plots:
        report = formation.run_gates(args.config, args.runs, args.seed, args.params)
        print(formation.format_report(report))
        write_json(args.json, formation.report_json(report))
        if plots is not None:
            from torchtrack.scenarios._formation_plots import plot_formation

            # show the run where the ellipsoidal gate loses most associations (stated in the figure titles)
            ell = report.results["ellipsoidal"]
            run_idx = int((ell["detected"] & ~ell["correct"]).sum((1, 2)).argmax())
            paths = plot_formation(report.data, {report.names[g]: r["estimate"] for g, r in report.results.items()},
                                   plots, run_idx)
    if args.plot is not None:
        print("plots: " + ", ".join(str(args.plot / p.name) for p in paths))
    return 0 if all(math.isfinite(v) for v in report.gate_volume.values()) else 1
