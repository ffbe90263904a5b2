"""``torchtrack train-detector``: train the CenterTrack-style detector (also under ``torchrun``)."""

from __future__ import annotations

from pathlib import Path

from torchtrack.cli._common import add_common_options, add_force_option, config_file, nonnegative_int, positive_int
from torchtrack.cli._labelled import add_labelled_options, check_labelled_options, load_labelled
from torchtrack.io.outputs import write_json

NAME = "train-detector"
HELP = "train the small CenterTrack-style detector on synthetic satellite video"
DESCRIPTION = HELP + """

Data are generated once and cached (data.cache); every epoch writes OUT/last.pt and, when the
validation F1 improves, OUT/best.pt. --resume continues from OUT/last.pt. Runs unchanged under
  torchrun --nproc_per_node N -m torchtrack train-detector --config configs/detector.yaml
(gloo on CPU, NCCL on GPU; the global batch is split among the processes).
Example: torchtrack train-detector --config configs/detector.yaml --seed 0

--finetune WEIGHTS adapts trained weights to labelled real frames (--images with --gt or --truth-csv,
optionally only inside --region), mixing in synthetic pairs; its settings are the finetune section of
--config (built-in defaults where it has none); it writes OUT/last.pt (default
finetune.out) and, with --export, the weights as the shipped file is written (decoding threshold kept).
Example: torchtrack train-detector --finetune torchtrack/detector/weights/centertrack_small.pt \\
  --images data/wpafb-aoi02/frames --truth-csv data/wpafb-aoi02/transformed_object_states.csv \\
  --region 0 0 284 496 --export out/finetuned.pt

--adapt adapts the weights (--weights, default the shipped ones) to a video without labels (--frames DIR or
--video FILE): in each of up to --rounds rounds the video pipeline tracks the video, the tracks kept over 8
frames or more become pseudo-labels, the detections no such track explains are left out of the loss (neither
vehicle nor background), and the weights are fine-tuned on them with synthetic pairs mixed in (the finetune
section of --config); the rounds stop early when the pseudo-labels change by less than 5 %. Writes OUT
(default out/detector-adapt): round-K/weights.pt, round-K/pipeline/ (that round's tracks), report.json and
adapt.png (pseudo-labels and their change per round); --export PT gets the last round's weights, which
track --weights and the Python API take.
Example: torchtrack train-detector --adapt --frames my-video/frames --rounds 3 --export out/adapted.pt
"""


def add_arguments(parser) -> None:
    parser.add_argument("--config", type=config_file("detector"), default="detector",
                        help="YAML config or preset name (default: the preset detector, configs/detector.yaml)")
    parser.add_argument("--out", type=Path, default=None, help="checkpoint folder (overrides train.out)")
    parser.add_argument("--epochs", type=positive_int, default=None, help="number of epochs (overrides train.epochs)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    parser.add_argument("--export", type=Path, default=None, metavar="PT",
                        help="after training, write the best checkpoint's weights (no optimizer) to PT, with "
                             "the decoding threshold calibrated on the validation sequences (with --finetune: "
                             "the last weights, threshold of WEIGHTS)")
    parser.add_argument("--finetune", type=Path, default=None, metavar="WEIGHTS",
                        help="fine-tune these weights on the labelled frames of --images instead of training")
    add_labelled_options(parser, "to fine-tune on")
    parser.add_argument("--adapt", action="store_true",
                        help="adapt the weights to the video of --frames or --video without labels (see above)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--frames", type=Path, default=None, metavar="DIR", help="--adapt: a folder of frames")
    source.add_argument("--video", type=Path, default=None, metavar="FILE", help="--adapt: a video file")
    parser.add_argument("--rounds", type=positive_int, default=3, help="--adapt: at most this many rounds (default 3)")
    parser.add_argument("--weights", type=Path, default=None, metavar="PT",
                        help="--adapt: the weights to start from (default: the shipped ones)")
    add_force_option(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch intra-op threads per process (1 is fastest on a busy machine)")
    parser.add_argument("--workers", type=nonnegative_int, default=0,
                        help="data-loading processes per training process (default 0: in the training process); "
                             "the result does not depend on it, since every sample is a pure function of its index")
    add_common_options(parser)


def run(args) -> int:
    import dataclasses
    import os

    from torchtrack.detector.checkpoint import load_checkpoint
    from torchtrack.detector.config import load_config
    from torchtrack.detector.dataset import build_cache
    from torchtrack.detector.train import export_weights, train
    from torchtrack.io.outputs import check_output_folder
    from torchtrack.threads import torch_threads

    check_labelled_options(args)
    if args.adapt or args.frames is not None or args.video is not None:
        return _adapt(args)
    if args.finetune is not None or args.images is not None:
        return _finetune(args)
    cfg = load_config(args.config)
    changes = {"out": None if args.out is None else str(args.out), "epochs": args.epochs}
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, **{k: v for k, v in changes.items() if v}))
    check_output_folder(cfg.train.out, "--out")
    check_output_folder(cfg.data.cache, f"{args.config or 'the detector config'}: data.cache")
    with torch_threads(args.threads):
        result = train(cfg, seed=args.seed, resume=args.resume, progress=not args.no_progress, workers=args.workers)
        if int(os.environ.get("RANK", "0")) != 0:
            return 0
        if args.export is not None:
            path = export_weights(result["best"], args.export, {"seed": args.seed, "command": "torchtrack "
                                  f"train-detector --config {args.config} --seed {args.seed}"},
                                  calibrate=build_cache(cfg, "val", args.seed))
            thr = load_checkpoint(path)["config"].decode.threshold
            print(f"exported {result['best']} to {args.export} (decoding threshold {thr} calibrated on the "
                  "validation sequences)")
    write_json(args.json, result)
    return 0


def _finetune(args) -> int:
    import dataclasses

    from torchtrack.detector.checkpoint import load_checkpoint
    from torchtrack.detector.config import load_config
    from torchtrack.detector.finetune import finetune
    from torchtrack.detector.train import export_weights
    from torchtrack.errors import TorchtrackError
    from torchtrack.threads import torch_threads

    if args.finetune is None or args.images is None:
        raise TorchtrackError("--finetune WEIGHTS and --images DIR go together")
    clash = [name for name, on in (("--epochs", args.epochs), ("--resume", args.resume),
                                   ("--workers", args.workers)) if on]
    if clash:
        raise TorchtrackError(f"{clash[0]} does not apply to --finetune (its settings: the finetune section of "
                              "--config)")
    base = load_checkpoint(args.finetune)
    settings = load_config(args.config).finetune
    if args.out is not None:
        settings = dataclasses.replace(settings, out=str(args.out))
    cfg = dataclasses.replace(base["config"], finetune=settings)
    data, region = load_labelled(args, settings.registration)
    with torch_threads(args.threads):
        result = finetune(cfg, base["model"], data, region, seed=args.seed, progress=not args.no_progress)
    if args.export is not None:
        truth = args.gt if args.gt is not None else args.truth_csv
        command = (f"torchtrack train-detector --finetune {args.finetune} --images {args.images} "
                   f"--{'gt' if args.gt is not None else 'truth-csv'} {truth} --region {' '.join(map(str, region))} "
                   f"--config {args.config} --seed {args.seed}")
        export_weights(result["last"], args.export, {"seed": args.seed, "command": command,
                                                      "finetuned_from": str(args.finetune)})
        print(f"exported {result['last']} to {args.export}")
    write_json(args.json, result)
    return 0


def _adapt(args) -> int:
    import dataclasses
    import shutil

    from torchtrack.detector.config import load_config
    from torchtrack.errors import TorchtrackError
    from torchtrack.io.frames import open_frames
    from torchtrack.io.outputs import OutputFolder, atomic_file, check_output_file
    from torchtrack.pipeline.adapt import AdaptSettings, adapt, load_frames
    from torchtrack.threads import torch_threads

    if not args.adapt or (args.frames is None and args.video is None):
        raise TorchtrackError("--adapt needs --frames DIR or --video FILE (and they need --adapt)")
    clash = [name for name, on in (("--finetune", args.finetune), ("--images", args.images), ("--epochs", args.epochs),
                                   ("--resume", args.resume), ("--workers", args.workers)) if on]
    if clash:
        raise TorchtrackError(f"{clash[0]} does not apply to --adapt")
    if args.export is None:
        raise TorchtrackError("--adapt needs --export PT (where the adapted weights go)")
    out = args.out if args.out is not None else Path("out/detector-adapt")
    check_output_file(args.export, "--export")
    source = args.frames if args.frames is not None else args.video
    frames = load_frames(open_frames(source), f"--{'frames' if args.frames is not None else 'video'} {source}")
    settings = load_config(args.config).finetune
    folder = OutputFolder(out, "torchtrack train-detector --adapt", args.force, inputs=[source])
    with torch_threads(args.threads), folder as staging:
        report = adapt(frames, staging, args.weights, dataclasses.replace(AdaptSettings(), rounds=args.rounds),
                       settings, seed=args.seed, progress=not args.no_progress)
        with atomic_file(args.export) as tmp:
            shutil.copyfile(staging / report["weights"], tmp)
    print(f"adapted in {len(report['rounds'])} round(s), {report['seconds']:.0f} s: {args.export} "
          f"(report: {out / 'report.json'})")
    write_json(args.json, report)
    return 0
