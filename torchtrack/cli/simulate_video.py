"""``torchtrack simulate-video``: a synthetic satellite-style sequence with truth and camera motion."""

from __future__ import annotations

from pathlib import Path

import torch

from torchtrack.cli._common import (
    VIDEO_PRESETS,
    add_common_options,
    add_force_option,
    bounded,
    config_file,
    positive_int,
)
from torchtrack.io.outputs import OutputFolder, write_json

NAME = "simulate-video"
HELP = "write a synthetic satellite-style sequence: frames, gt.txt (MOTChallenge), camera.json"
DESCRIPTION = HELP + """

Output folder: frames/000001.png ... (or video.mp4 with --format mp4), gt.txt
(frame,id,x,y,w,h,conf,-1,-1,-1; boxes of gt_box_size px centred on the vehicles), velocity.txt
(frame,id,vx,vy,moving) and camera.json (true reference->frame homographies). The folder appears as one
set when the sequence is complete (written in OUT.partial until then); an existing --out is replaced only
when it holds the output of torchtrack simulate-video (or with --force).
Example: torchtrack simulate-video --out out/seq --frames 30 --seed 1
"""


def add_arguments(parser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--config", type=config_file(*VIDEO_PRESETS), default=None,
                        help="YAML config or preset name (default: built-in, same as the preset video)")
    parser.add_argument("--frames", type=positive_int, default=None, help="number of frames (overrides the config)")
    parser.add_argument("--size", type=bounded(int, ge=32), nargs=2, default=None, metavar=("H", "W"),
                        help="frame height and width (overrides the config)")
    parser.add_argument("--format", choices=["png", "mp4", "avi"], default="png",
                        help="frames as PNG files (default) or one video file")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_force_option(parser)
    add_common_options(parser)


def run(args) -> int:
    from torchtrack.sim.video import load_video_config, write_sequence

    cfg = load_video_config(args.config)
    if args.frames is not None:
        cfg = cfg.replace(frames=args.frames)
    if args.size is not None:
        cfg = cfg.replace(height=args.size[0], width=args.size[1])
    with OutputFolder(args.out, f"torchtrack {NAME}", args.force, inputs=[args.config]) as staging:
        write_sequence(cfg, torch.Generator().manual_seed(args.seed), staging, args.format,
                       progress=not args.no_progress)
        n_gt = sum(1 for _ in open(staging / "gt.txt"))
    out = args.out
    print(f"wrote {cfg.frames} frames of {cfg.height}x{cfg.width}, {n_gt} truth rows to {out}")
    write_json(args.json, {"out": str(out), "frames": cfg.frames, "gt_rows": n_gt})
    return 0
