"""``torchtrack bench clearmot``: the options and the output of :mod:`torchtrack.bench.clearmot`."""

from torchtrack.bench import clearmot
from torchtrack.bench._timing import format_result
from torchtrack.cli._common import positive_int
from torchtrack.cli.bench import report

NAME = "clearmot"
HELP = "CLEAR-MOT evaluation throughput vs py-motmetrics"
DESCRIPTION = """CLEAR-MOT evaluation throughput (frames scored per second) against py-motmetrics, timed in the
same run.

Workload: --frames frames of --objects random-walk objects in a 400 x 400 px area, one prediction per
object (truth plus 3 px noise, 5 % of them under a wrong identity), centre-distance gate 10 px. Both
libraries compute all the CLEAR-MOT scores (IDF1 included) and must give the same counts (checked).
py-motmetrics is a test-only dependency (pip install torchtrack-mtt[test]); without it only torchtrack's
rate is printed.

Example: torchtrack bench clearmot --frames 200 --objects 50
"""


def add_arguments(parser) -> None:
    parser.add_argument("--frames", type=positive_int, default=512, help="frames (default 512)")
    parser.add_argument("--objects", type=positive_int, default=100, help="objects and predictions per frame")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats, best kept (default 3)")


def run(args) -> int:
    result = clearmot.measure(args.frames, args.objects, args.repeats, args.seed)
    return report(args, result, format_result(result))
