"""``torchtrack tune --config configs/tune-*.yaml``: fit filter parameters by gradient."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

NAME = "tune"
HELP = "fit filter parameters (noise, p_D, clutter, birth, transition matrices) to data by gradient"
DESCRIPTION = """Fit the trainable parameters of a filter to data by gradient descent.

The YAML config names the filter (kalman, imm, gmphd, pf), its builder options (start values), the
trainable parameters by dotted name (everything else frozen), the data (simulated or from files,
split into training and held-out sequences or windows), the loss (marginal log-likelihood, PHD
predictive likelihood, particle estimate, soft GOSPA) and the optimiser (adam or lbfgs, mini-batches,
early stopping on the held-out loss). See docs/tune.md.

Writes OUT/params.yaml (the fitted parameters, which torchtrack track --params (GM-PHD) and torchtrack
scenario maneuver|formation --params (Kalman, IMM) read; for the GM-PHD OUT/track.yaml is also a torchtrack
track --config file) and OUT/loss.png (the loss curve). An optional refine section adds a line search on the task metric
(MOTA) over the training items after the gradient fit. A non-finite loss stops training, keeps the
last parameters with a finite loss, writes them, and exits with status 1. The output folder appears as one
set when the run completes (written in OUT.partial until then; the config's output.params/output.plot
do not apply); an existing OUT is replaced only when it holds the output of torchtrack tune (or with
--force).

Examples:
  torchtrack tune --config configs/tune-kalman.yaml
  torchtrack tune --config configs/tune-gmphd-wpafb.yaml --out out/tune-gmphd --json out/tune-gmphd.json
  torchtrack tune --config configs/tune-gmphd-wpafb.yaml --set data.held_out_frames=[1,128] \\
      --set 'data.train_frames=[[129,512]]'        # another held-out block
  torchtrack tune --config configs/tune-gmphd-wpafb.yaml --folds 4 --json out/tune-gmphd-cv.json
                                                   # each quarter of frames 1-512 held out in turn
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from torchtrack.cli._common import (
        TUNE_PRESETS,
        add_common_options,
        add_force_option,
        bounded,
        config_file,
        positive_int,
    )

    parser.add_argument("--config", type=config_file(*TUNE_PRESETS), required=True, metavar="YAML",
                        help="tune config: a path or a preset name (configs/tune-*.yaml, e.g. tune-kalman)")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="output folder (default: the config's output.dir, else out/tune-FILTER)")
    parser.add_argument("--threads", type=positive_int, default=1,
                        help="torch CPU threads (default 1: small per-step matrices are fastest on one thread)")
    parser.add_argument("--loss", default=None, help="override the config's loss (e.g. gospa)")
    parser.add_argument("--no-grid", action="store_true", help="skip the config's grid-search baseline")
    parser.add_argument("--no-refine", action="store_true", help="skip the config's line search on the task metric")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--folds", type=bounded(int, ge=2), default=None, metavar="K",
                        help="K-fold cross-validation: hold out each of K contiguous blocks of the frames (or "
                             "items) in turn, tune (and run the grid) on the rest, report per fold and the mean; "
                             "outputs under OUT/fold-1 ... OUT/fold-K")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config entry (dotted key, YAML value; repeatable), e.g. "
                             "--set data.held_out_frames=[1,128] --set 'data.train_frames=[[129,512]]'")
    add_force_option(parser)
    add_common_options(parser, seed=None, seed_help="random seed (default: the config's seed, else 0)")


def _rows(report: dict) -> list[list]:
    truth, rel = report["truth"], report["relative_error"]
    return [[name, _fmt(report["start"].get(name)), _fmt(fitted), _fmt(truth[name]) if name in truth else "-",
             f"{100 * rel[name]:.1f}%" if name in rel else "-"] for name, fitted in report["fitted"].items()]


def _fmt(v) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _print_folds(summary: dict) -> None:
    from torchtrack.metrics.table import format_table

    runs = summary["runs"]
    where = (f"mean over {len(runs[0]['held_out_draws']['seeds'])} further detection draws of each held-out block"
             if "held_out_draws" in runs[0] else "held-out items")
    first = summary["per_fold"]["tuned"][0]
    metrics = [k for k in ("MOTA", "OSPA", "IDS") if k in first] or list(first)
    methods = list(summary["per_fold"])
    rows = []
    for i, report in enumerate(runs):
        held = report.get("held_out_frames")
        label = f"frames {held[0]}-{held[1]}" if held else f"{report['held_out_items']} items"
        scores = [summary["per_fold"][m][i] for m in methods]
        rows.append([f"{report['fold']}: {label}", *[s.get(k, float("nan")) for s in scores for k in metrics]])
    rows.append(["mean", *[summary["mean"][m].get(k, float("nan")) for m in methods for k in metrics]])
    names = list(runs[0]["fitted"])
    print("\nfitted per fold:")
    print(format_table(["fold", *names], [[r["fold"], *[_fmt(r["fitted"][n]) for n in names]] for r in runs]))
    print(f"\n{summary['folds']}-fold cross-validation ({where}):")
    print(format_table(["fold", *[f"{m} {k}" for m in methods for k in metrics]], rows, floatfmt=".4g"))
    if "difference" in summary:
        d = summary["difference"]
        ahead = sum(x >= 0 for x in d["per_fold"])
        print(f"tuned - grid {d['metric']}: {d['mean']:+.4f} (standard error {d['stderr']:.4f}); tuned at least "
              f"as good in {ahead} of {summary['folds']} folds")
    evals = sum(r["filter_evaluations"] for r in runs)
    line = f"filter evaluations: tuned {evals}"
    if "grid" in runs[0]:
        line += f", grid {sum(r['grid']['filter_evaluations'] for r in runs)}"
    print(line + f"; outputs under {Path(runs[0]['output']['params']).parent.parent}")


def _final_paths(report: dict, folder) -> None:
    """The report's output files where they are after the commit (they were written to the staging folder)."""
    report["output"] = {key: str(folder.final(path)) for key, path in report["output"].items()}


def run(args) -> int:
    import torch

    from torchtrack.io.outputs import OutputFolder, write_json
    from torchtrack.metrics.table import format_table
    from torchtrack.threads import clamp_threads
    from torchtrack.tuning.config import read_tune_config
    from torchtrack.tuning.tune import output_dir, tune

    torch.set_num_threads(clamp_threads(args.threads))
    config = read_tune_config(args.config, args.set)
    if args.loss:
        config["loss"] = args.loss
    if args.no_grid:
        config.pop("grid", None)
    if args.no_refine:
        config.pop("refine", None)
    folder = OutputFolder(output_dir(config, args.out), f"torchtrack {NAME}", args.force, inputs=[args.config])
    if args.folds is not None:
        from torchtrack.tuning.crossval import cross_validate

        with folder as staging:
            summary = cross_validate(config, args.folds, out=staging, seed=args.seed, progress=not args.no_progress)
        for report in summary["runs"]:
            _final_paths(report, folder)
        _print_folds(summary)
        write_json(args.json, summary)
        return 1 if any(r["stopped"] == "non-finite" for r in summary["runs"]) else 0
    with folder as staging:
        report = tune(config, out=staging, seed=args.seed, progress=not args.no_progress)
    _final_paths(report, folder)
    print(format_table(["parameter", "start", "fitted", "truth", "error"], _rows(report)))
    before, after = report["held_out_before"], report["held_out_after"]
    print("\n" + format_table(["held-out", "before", "after"],
                              [[k, float(before[k]), float(after[k])] for k in before if k in after], floatfmt=".4g"))
    fit = report.get("fit", report)
    print(f"\n{report['steps']} steps ({report['stopped']}; kept step {report['best_step']}), "
          f"{fit['filter_evaluations']} item evaluations ({fit['frames']} frames), {fit['seconds']:.1f} s")
    if "refine" in report:
        r = report["refine"]
        chosen = f" (best point {r['best']:.4g}, chose the mean of the {r['average']} best)" if r["average"] > 1 else ""
        print(f"refine: training {r['metric']} {r['start']:.4g} -> {r['final']:.4g}{chosen} in "
              f"{r['metric_evaluations']} evaluations ({r['filter_evaluations']} items, {r['frames']} frames), "
              f"{r['seconds']:.1f} s; total {report['filter_evaluations']} item evaluations "
              f"({report['frames']} frames)")
    metrics = [k for k in ("MOTA", "OSPA", "IDS") if k in after]
    if "grid" in report or "refine" in report:
        rows = [["start", "-", "-", *[before.get(k, float("nan")) for k in metrics], "-"]]
        if "refine" in report:
            rows.append(["gradient fit", fit["filter_evaluations"], fit["frames"],
                         *[fit["held_out"].get(k, float("nan")) for k in metrics], f"{fit['seconds']:.1f}"])
        rows.append(["gradient fit + refine" if "refine" in report else "gradient fit", report["filter_evaluations"],
                     report["frames"], *[after[k] for k in metrics], f"{report['seconds']:.1f}"])
        if "grid" in report:
            g = report["grid"]
            rows.append([f"grid ({g['combinations']} points)", g["filter_evaluations"], g["frames"],
                         *[g["held_out"].get(k, float("nan")) for k in metrics], f"{g['seconds']:.1f}"])
        print()
        print(format_table(["held-out", "item evaluations", "frames", *metrics, "seconds"], rows, floatfmt=".4g"))
    if "held_out_draws" in report:
        draws = report["held_out_draws"]
        seeds = draws["seeds"]
        print(f"\nheld-out frames, {len(seeds)} further detection draws (seeds {', '.join(map(str, seeds))}), mean:")
        rows = [[name, *[draws[name].get(k, float("nan")) for k in metrics]]
                for name in ("tuned", "grid") if name in draws]
        print(format_table(["held-out draws", *metrics], rows, floatfmt=".4g"))
    for key, path in report["output"].items():
        print(f"{key}: {path}")
    write_json(args.json, report)
    if report["stopped"] == "non-finite":
        print(f"torchtrack tune: warning: {report['message']}", file=sys.stderr)
        return 1
    return 0
