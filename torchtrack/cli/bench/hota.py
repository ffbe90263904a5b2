"""``torchtrack bench hota``: the options and the output of :mod:`torchtrack.bench.hota`."""

from pathlib import Path

from torchtrack.bench import hota
from torchtrack.bench._timing import format_result
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import read_mot
from torchtrack.io.outputs import write_json

NAME = "hota"
HELP = "HOTA evaluation throughput vs TrackEval's HOTA metric class"
DESCRIPTION = hota.__doc__


def add_arguments(parser) -> None:
    parser.add_argument("--gt", type=Path, help="ground truth (MOTChallenge text) instead of the synthetic workload")
    parser.add_argument("--pred", type=Path, help="tracker output (MOTChallenge text), with --gt")
    parser.add_argument("--frames", type=int, default=512, help="synthetic workload: frames (default 512)")
    parser.add_argument("--objects", type=int, default=85, help="synthetic workload: objects per frame (85)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats, best kept (default 3)")


def run(args) -> int:
    if (args.gt is None) != (args.pred is None):
        raise TorchtrackError("--gt and --pred go together")
    if args.frames < 1 or args.objects < 1 or args.repeats < 1:
        raise TorchtrackError("--frames, --objects and --repeats must be positive")
    gt, pred = (read_mot(args.gt), read_mot(args.pred)) if args.gt is not None else (None, None)
    result = hota.measure(gt, pred, args.frames, args.objects, args.repeats, args.seed)
    print(format_result(result))
    extra = result.extra
    if extra.get("reference_prepare_seconds") is not None:
        print(f"TrackEval's preparation of the similarities (not timed above): "
              f"{extra['reference_prepare_seconds']:.3f} s; ratio including it {extra['ratio_with_preparation']:.1f}x;"
              f" scores agree: {extra['scores_agree']}")
    write_json(args.json, result.payload())
    return 0
