"""``torchtrack bench clearmot``: the options and the output of :mod:`torchtrack.bench.clearmot`."""

from torchtrack.bench import clearmot
from torchtrack.bench._timing import format_result
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import write_json

NAME = "clearmot"
HELP = "CLEAR-MOT evaluation throughput vs py-motmetrics"
DESCRIPTION = clearmot.__doc__


def add_arguments(parser) -> None:
    parser.add_argument("--frames", type=int, default=512, help="frames (default 512)")
    parser.add_argument("--objects", type=int, default=100, help="objects and predictions per frame (100)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats, best kept (default 3)")


def run(args) -> int:
    if args.frames < 1 or args.objects < 1:
        raise TorchtrackError("--frames and --objects must be positive")
    result = clearmot.measure(args.frames, args.objects, args.repeats, args.seed)
    print(format_result(result))
    write_json(args.json, result.payload())
    return 0
