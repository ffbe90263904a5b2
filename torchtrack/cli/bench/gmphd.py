"""``torchtrack bench gmphd``: the options and the output of :mod:`torchtrack.bench.gmphd`."""

import argparse

from torchtrack.bench import gmphd
from torchtrack.bench.gmphd import WORKLOADS
from torchtrack.cli.bench import add_threads_option
from torchtrack.io.outputs import write_json
from torchtrack.threads import torch_threads

NAME = "gmphd"
HELP = "GM-PHD steps/s (Stone Soup tutorial setting and a WPAFB-scale frame) vs a per-component NumPy GM-PHD"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workload", choices=[*WORKLOADS, "all"], default="all", help="workload (default all)")
    parser.add_argument("--steps", type=int, default=None, help="steps timed for torchtrack (default: workload's)")
    parser.add_argument("--reference-steps", type=int, default=20, help="steps timed for the NumPy reference "
                        "(default 20)")
    parser.add_argument("--repeats", type=int, default=5, help="timed passes of the whole sequence, the fastest kept "
                        "(default 5; slower passes are the machine's noise)")
    add_threads_option(parser)


def run(args) -> int:
    with torch_threads(args.threads):
        return _run(args)


def _run(args) -> int:
    overhead = gmphd.op_overhead_us()
    print(f"one tiny torch op costs {overhead:.1f} us of CPU now (about 1-2 us on an idle core)")
    results = {}
    for wname in list(WORKLOADS) if args.workload == "all" else [args.workload]:
        result = gmphd.measure(wname, overhead, args.steps, args.reference_steps, args.repeats, args.seed)
        print(gmphd.format_workload(wname, result))
        results[wname] = result.payload()
    write_json(args.json, results if len(results) > 1 else next(iter(results.values())))
    return 0
