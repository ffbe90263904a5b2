"""``torchtrack bench scale``: the options and the output of :mod:`torchtrack.bench.scale`."""

import argparse
from pathlib import Path

from torchtrack.bench import scale
from torchtrack.cli._common import positive_float, positive_int
from torchtrack.filters.multitarget import tracker_names
from torchtrack.io.outputs import write_json

NAME = "scale"
HELP = "every tracker's frames/s, MOTA and peak memory as vehicles per frame grow at constant density"
DESCRIPTION = scale.__doc__ + """
A quick run on a 2-core machine (about a minute): --vehicles 100 1000 --frames 20 --trackers gmphd sort"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vehicles", type=positive_int, nargs="+", default=[100, 300, 1000, 3000, 10000],
                        help="vehicles per frame N (default 100 300 1000 3000 10000)")
    parser.add_argument("--trackers", nargs="+", choices=tracker_names(), default=None,
                        help="trackers to run (default: all)")
    parser.add_argument("--frames", type=positive_int, default=40, help="frames per run (default 40)")
    parser.add_argument("--device", default="cpu", help="torch device of the detections (default cpu)")
    parser.add_argument("--max-seconds", type=positive_float, default=120.0,
                        help="a run stops after this much tracker time and the tracker's larger N are skipped "
                             "(default 120)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--plot", type=Path, default=None, metavar="PNG",
                        help="write frames/s and MOTA against N to this PNG")


def run(args) -> int:
    rows = scale.measure(args.vehicles, args.trackers, args.frames, args.device, args.max_seconds, args.threads,
                         args.seed, progress=scale.print_progress)
    workload = scale.workload(args.frames, args.device, args.threads)
    print(scale.format_report(rows, workload))
    write_json(args.json, scale.payload(rows, workload))
    if args.plot is not None:
        scale.plot(rows, args.plot, workload)
    return 0
