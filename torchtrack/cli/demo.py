"""``torchtrack demo``: synthetic sequence → registration → shipped detector → all trackers → Table 1."""

from __future__ import annotations

from pathlib import Path

from torchtrack.cli._common import PIPELINE_PRESETS, add_common_options, add_force_option, config_file, positive_int
from torchtrack.io.outputs import OutputFolder, write_json
from torchtrack.pipeline.config import load_pipeline_config
from torchtrack.pipeline.demo import format_demo, run_demo

NAME = "demo"
HELP = "the main job: synthetic video → detector → GM-PHD and the other trackers → CLEAR-MOT table, video, plots"
DESCRIPTION = """\
Generate the embedded default synthetic satellite-style sequence (512x512), register it, detect with the
shipped detector weights (once), track with the enhanced GM-PHD and with every other tracker on the same
detections, and print the CLEAR-MOT table in the layout of Table 1 of Aguilar et al. (ICASSP 2023).

Writes under --out: annotated.mp4 (enhanced GM-PHD tracks, truth as white crosses), tracks.txt
(MOTChallenge), detections.txt, metrics.json, tracks_first_frame.png, scores.png, frame_*.png,
trackers/<name>.txt and the generated sequence in sequence/. The files appear in --out as one set when
the run completes (written in OUT.partial until then); an existing --out is replaced only when it holds
the output of torchtrack demo (or with --force).
"""


def add_arguments(parser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    parser.add_argument("--frames", type=positive_int, default=None, metavar="N",
                        help="frames to generate (default: the embedded default, 60)")
    parser.add_argument("--truth", choices=("moving", "all"), default="moving",
                        help="moving: the vehicles that the sequence's velocity.txt flags as driving are the "
                             "targets, parked ones don't-care (the paper's protocol, as eval --moving scores "
                             "them; default); all: every vehicle is a target")
    parser.add_argument("--config", type=config_file(*PIPELINE_PRESETS), default=None, metavar="YAML",
                        help="pipeline settings, a path or a preset name (e.g. pipeline-online); default: the "
                             "embedded ones (the preset pipeline)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_force_option(parser)
    add_common_options(parser)


def run(args) -> int:
    config = load_pipeline_config(args.config) if args.config else None
    with OutputFolder(args.out, f"torchtrack {NAME}", args.force, inputs=[args.config]) as staging:
        metrics = run_demo(staging, seed=args.seed, frames=args.frames, truth=args.truth, config=config,
                           progress=not args.no_progress)
    print(format_demo(metrics))
    print(f"wrote {args.out}/annotated.mp4, tracks.txt, metrics.json, tracks_first_frame.png, scores.png")
    write_json(args.json, metrics)
    return 0
