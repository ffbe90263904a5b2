"""``torchtrack bench scale``: the options and the output of :mod:`torchtrack.bench.scale` (vehicles per frame)
and, with ``--frame-sizes``, of :mod:`torchtrack.bench.frames` (the pipeline over frame sizes)."""

import argparse
import tempfile
from pathlib import Path

from torchtrack.bench import frames, scale
from torchtrack.cli._common import add_force_option, bounded, positive_float, positive_int
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.protocol import tracker_names
from torchtrack.io.outputs import OutputFolder, write_json

NAME = "scale"
HELP = ("every tracker's frames/s, MOTA and peak memory as vehicles per frame grow at constant density; with "
        "--frame-sizes the pipeline's megapixels/s, memory, MOTA and detection F1 as frames grow")
DESCRIPTION = """How the trackers and the video pipeline scale.

Vehicles per frame (the default): N vehicles, one per 60 x 60 px, each moving in a straight line at 2.5 to
3.5 px/frame, detected with p_D 0.9 and 1 px noise (with the detector's velocity), N / 4 clutter detections
per frame. Every tracker runs at its built-in defaults on the same detections. Printed per tracker and N:
frames/s of the tracker alone (per wall second and per CPU second), MOTA at 10 px, the CPU cost per
vehicle-frame relative to the smallest N, the component cap hits and the peak memory. A run that passes
--max-seconds of tracker time stops there, and that tracker's larger N are skipped.

Frame sizes (--frame-sizes): synthetic S x S sequences of the same number of frames at every size run
through the pipeline as torchtrack track --sequences DIR --no-video runs them (registration, the detector in
tiles, the enhanced GM-PHD). Printed per size: megapixels per second end to end and per stage, the peak
memory, MOTA over the moving vehicles, the detector's F1 and the registration error against the true camera.

Examples (2-core CPU):
  torchtrack bench scale --vehicles 100 1000 --frames 20 --trackers gmphd sort   # about a minute
  torchtrack bench scale --frame-sizes 256 512 1024 --frames 6                   # about 15 s
"""

VEHICLES = [100, 300, 1000, 3000, 10000]
VEHICLE_FRAMES = 40
MAX_SECONDS = 120.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vehicles", type=positive_int, nargs="+", default=None,
                        help=f"vehicles per frame N (default {' '.join(map(str, VEHICLES))})")
    parser.add_argument("--trackers", nargs="+", choices=tracker_names(), default=None,
                        help="trackers to run (default: all)")
    parser.add_argument("--frames", type=positive_int, default=None,
                        help=f"frames per run (default {VEHICLE_FRAMES}); with --frame-sizes frames per sequence, "
                             f"the same at every size (default {frames.FRAMES})")
    parser.add_argument("--device", default="cpu", help="torch device of the detections (default cpu); with "
                        "--frame-sizes of the detector's network and the tracker")
    parser.add_argument("--max-seconds", type=positive_float, default=None,
                        help="a run stops after this much tracker time and the tracker's larger N are skipped "
                             f"(default {MAX_SECONDS:g})")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--plot", type=Path, default=None, metavar="PNG",
                        help="write frames/s and MOTA against N (with --frame-sizes: megapixels/s, peak memory, "
                             "MOTA and detection F1 against the frame size) to this PNG")
    g = parser.add_argument_group("frame sizes (the video pipeline end to end)")
    g.add_argument("--frame-sizes", type=bounded(int, ge=32), nargs="+", default=None, metavar="S",
                   help="run the pipeline (registration, detector, enhanced GM-PHD; no video) on synthetic "
                        "S × S frames instead of the trackers over N, e.g. 512 1024 2048 4096")
    g.add_argument("--sequences", type=positive_int, nargs="+", default=None, metavar="K",
                   help="sequences per frame size: one number for every size or one per size (default: the "
                        f"pixels of one sequence of the largest size, at most {frames.MAX_SEQUENCES})")
    g.add_argument("--out", type=Path, default=None,
                   help="keep the sequences and the pipeline's outputs in this folder (default: a temporary one): "
                        "OUT/S/sequences/seedN/ (the generator's folders), OUT/S/run/ (as track --sequences "
                        "writes it), OUT/warmup/ (the untimed first sequence), OUT/bench.json")
    add_force_option(parser)


def run(args) -> int:
    if args.frame_sizes is not None:
        return run_frame_sizes(args)
    given = [flag for flag, value in (("--sequences", args.sequences), ("--out", args.out)) if value is not None]
    if given:
        raise TorchtrackError(f"{', '.join(given)} apply to --frame-sizes only")
    frames_run = args.frames or VEHICLE_FRAMES
    rows = scale.measure(args.vehicles or VEHICLES, args.trackers, frames_run, args.device,
                         args.max_seconds or MAX_SECONDS, args.threads, args.seed, progress=scale.print_progress)
    workload = scale.workload(frames_run, args.device, args.threads)
    print(scale.format_report(rows, workload))
    write_json(args.json, scale.payload(rows, workload))
    if args.plot is not None:
        scale.plot(rows, args.plot, workload)
    return 0


def run_frame_sizes(args) -> int:
    given = [flag for flag, value in (("--vehicles", args.vehicles), ("--trackers", args.trackers),
                                      ("--max-seconds", args.max_seconds)) if value is not None]
    if given:
        raise TorchtrackError(f"{', '.join(given)} do not apply to --frame-sizes (the pipeline runs its enhanced "
                              "GM-PHD over every frame)")
    sizes = args.frame_sizes
    if len(set(sizes)) < len(sizes):
        raise TorchtrackError(f"--frame-sizes: each size once; got {' '.join(map(str, sizes))}")
    counts = args.sequences
    if counts is not None and len(counts) not in (1, len(sizes)):
        raise TorchtrackError(f"--sequences: give one count or one per frame size ({len(sizes)}); got {len(counts)}")
    if counts is not None and len(counts) == 1:
        counts = counts * len(sizes)
    frames_run = args.frames or frames.FRAMES
    workload = frames.workload(frames_run, args.device, args.threads)

    def measure(work: Path) -> list[frames.FrameSizeRow]:
        return frames.measure(sizes, work, frames_run, counts, args.device, args.threads, args.seed,
                              progress=frames.print_progress)

    if args.out is None:
        with tempfile.TemporaryDirectory(prefix="torchtrack-bench-frames-") as work:
            rows = measure(Path(work))
    else:
        with OutputFolder(args.out, "torchtrack bench scale --frame-sizes", args.force) as staging:
            rows = measure(staging)
            write_json(staging / "bench.json", frames.payload(rows, workload))
    print(frames.format_report(rows, workload))
    write_json(args.json, frames.payload(rows, workload))
    if args.plot is not None:
        frames.plot(rows, args.plot, workload)
    return 0
