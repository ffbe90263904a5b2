"""``torchtrack select-trackers``: choose the pipeline's min_speed and tracker options on validation sequences."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from torchtrack.cli._common import PIPELINE_PRESETS, add_common_options, add_force_option, config_file
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import tracker_names
from torchtrack.io.outputs import OutputFolder, check_output_file, write_json, write_yaml
from torchtrack.metrics.table import format_table, protocol
from torchtrack.pipeline.config import PipelineConfig, load_pipeline_config
from torchtrack.pipeline.selection import GRIDS, check_ids_reference, collect, select

NAME = "select-trackers"
HELP = "grid-search the video pipeline's moving-object gate and each tracker's options on validation sequences"
DESCRIPTION = """\
Run registration and the detector once on every sequence of --sequences (folders as for
torchtrack track --sequences, with gt.txt and, for synthetic ones, velocity.txt), then every tracker
with every option set of its grid (torchtrack/pipeline/selection.py: GRIDS) at every combination of
--min-speeds and --min-motions (the moving-object gate), scored by pooled CLEAR-MOT. Each tracker keeps
the options with the best IDF1 among those within --mota-tolerance of its best MOTA (with --max-ids-ratio
R, the pipeline's tracker only among the option sets with at most R times the identity switches of
--ids-reference's chosen options: fewer switches for some MOTA); the gate is where
the pipeline's tracker (--pipeline-config's, default gmphd) scores best, so all trackers are compared on
the same detections. Writes --out, a pipeline config for torchtrack demo --config and
torchtrack track --pipeline-config, and OUT.json with every run (each file appears whole: written under
a .partial name, then renamed; OUT.json first). The detection runs go to --work, one set written as
WORK.partial and moved into place when the selection completes; an existing --work is replaced only when
it holds the output of torchtrack select-trackers (or with --force).

Use sequences that are not the ones you report (docs/pipeline.md). Example:
  for i in 1 2 3; do torchtrack simulate-video --seed $((10000000 + i)) --out out/val/seq$i; done
  torchtrack select-trackers --sequences out/val --out out/pipeline-selected.yaml
"""


def add_arguments(parser) -> None:
    parser.add_argument("--sequences", type=Path, required=True, metavar="DIR", help="validation sequences")
    parser.add_argument("--out", type=Path, required=True, metavar="YAML", help="pipeline config to write")
    parser.add_argument("--pipeline-config", type=config_file(*PIPELINE_PRESETS), default=None, metavar="YAML",
                        help="starting pipeline settings (default: the embedded ones)")
    parser.add_argument("--trackers", nargs="+", choices=tracker_names(), default=None,
                        help="trackers to tune (default: all)")
    parser.add_argument("--min-speeds", nargs="+", type=float, default=[0.0, 2.0], metavar="V",
                        help="min_speed values to try, px/frame (default 0 2)")
    parser.add_argument("--min-motions", nargs="+", type=float, default=[0.0, 5.0, 8.0], metavar="G",
                        help="min_motion values to try, grey levels (default 0 5 8)")
    parser.add_argument("--mota-tolerance", type=float, default=0.005, metavar="T",
                        help="per tracker, keep the options with the best IDF1 among those within T of the best "
                             "MOTA (default 0.005; 0: the best MOTA)")
    parser.add_argument("--max-ids-ratio", type=float, default=None, metavar="R",
                        help="the pipeline's tracker chooses only among option sets with at most R times the "
                             "identity switches of --ids-reference's chosen options (default: no limit)")
    parser.add_argument("--ids-reference", choices=tracker_names(), default="labelled-gmphd",
                        help="tracker whose identity switches --max-ids-ratio refers to (default labelled-gmphd)")
    parser.add_argument("--work", type=Path, default=Path("out/select-trackers"), metavar="DIR",
                        help="folder for the detection runs (default out/select-trackers)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_force_option(parser, "--work")
    add_common_options(parser, random=False)


def config_mapping(config: PipelineConfig) -> dict:
    """The pipeline config as a YAML-ready mapping (the layout of configs/pipeline.yaml)."""
    data = dataclasses.asdict(config)
    data["snapshots"] = list(config.snapshots)
    return {"pipeline": data}


def run(args) -> int:
    if not args.mota_tolerance >= 0:
        raise TorchtrackError(f"--mota-tolerance must be >= 0, got {args.mota_tolerance}")
    for flag, values in (("--min-speeds", args.min_speeds), ("--min-motions", args.min_motions)):
        if any(v < 0 for v in values):
            raise TorchtrackError(f"{flag} must be >= 0, got {values}")
    if args.max_ids_ratio is not None and not args.max_ids_ratio > 0:
        raise TorchtrackError(f"--max-ids-ratio must be > 0, got {args.max_ids_ratio}")
    check_output_file(args.out)
    check_output_file(args.out.with_suffix(".json"), "--out (its .json)")
    config = load_pipeline_config(args.pipeline_config)
    trackers = args.trackers or tracker_names()
    if args.max_ids_ratio is not None:
        check_ids_reference(args.ids_reference, config, trackers)
    with OutputFolder(args.work, f"torchtrack {NAME}", args.force, flag="--work",
                      inputs=[args.sequences, args.pipeline_config, args.out]) as work:
        data = collect(args.sequences, work, config, progress=not args.no_progress)
        if not data:
            raise TorchtrackError(f"{args.sequences}: no sequence with a gt.txt")
        gates = [(s, m) for s in args.min_speeds for m in args.min_motions]
        ids_limit = None if args.max_ids_ratio is None else (args.ids_reference, args.max_ids_ratio)
        chosen, log = select(data, config, trackers, gates, GRIDS, progress=not args.no_progress,
                             mota_tolerance=args.mota_tolerance, ids_limit=ids_limit)
    flags = [f"--sequences {args.sequences}"]
    if args.pipeline_config is not None:
        flags.append(f"--pipeline-config {args.pipeline_config}")
    flags += [f"--min-speeds {' '.join(map(str, args.min_speeds))}",
              f"--min-motions {' '.join(map(str, args.min_motions))}", f"--mota-tolerance {args.mota_tolerance}"]
    if ids_limit is not None:
        flags.append(f"--max-ids-ratio {args.max_ids_ratio} --ids-reference {args.ids_reference}")
    header = f"# written by: torchtrack select-trackers {' '.join(flags)}\n"
    write_json(args.out.with_suffix(".json"), log, indent=1)  # the log first: the config appears last
    write_yaml(args.out, config_mapping(chosen), header)
    best = {r["tracker"]: r for r in log if (r["min_speed"], r["min_motion"]) == (chosen.min_speed, chosen.min_motion)
            and r["options"] == chosen.trackers.get(r["tracker"], {})}
    rows = [[n, *(100 * best[n][k] for k in ("MOTA", "HOTA", "IDF1")), *(best[n][k] for k in ("IDS", "FP", "FN")),
             json.dumps(best[n]["options"])] for n in trackers if n in best]
    print(f"{len(data)} sequences, {len(log)} tracker runs; min_speed {chosen.min_speed} px/frame, "
          f"min_motion {chosen.min_motion}")
    print(protocol(True, config.threshold))
    print(format_table(["tracker", "MOTA (%)", "HOTA (%)", "IDF1 (%)", "IDS", "FP", "FN", "options"], rows,
                       floatfmt=".2f"))
    print(f"wrote {args.out} and {args.out.with_suffix('.json')}")
    write_json(args.json, {"min_speed": chosen.min_speed, "min_motion": chosen.min_motion,
                           "trackers": chosen.trackers, "runs": log})
    return 0
