"""``torchtrack bench clearmot``: the options and the output of :mod:`torchtrack.bench.clearmot`."""

from torchtrack.bench import clearmot
from torchtrack.bench._timing import format_result
from torchtrack.cli._common import positive_int
from torchtrack.cli.bench import report

NAME = "clearmot"
HELP = "CLEAR-MOT evaluation throughput vs py-motmetrics"
DESCRIPTION = clearmot.__doc__


def add_arguments(parser) -> None:
    parser.add_argument("--frames", type=positive_int, default=512, help="frames (default 512)")
    parser.add_argument("--objects", type=positive_int, default=100, help="objects and predictions per frame (100)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats, best kept (default 3)")


def run(args) -> int:
    result = clearmot.measure(args.frames, args.objects, args.repeats, args.seed)
    return report(args, result, format_result(result))
