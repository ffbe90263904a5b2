"""``torchtrack bench hota``: the options and the output of :mod:`torchtrack.bench.hota`."""

from pathlib import Path

from torchtrack.bench import hota
from torchtrack.bench._timing import format_result
from torchtrack.cli._common import positive_int
from torchtrack.cli.bench import report
from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import read_mot

NAME = "hota"
HELP = "HOTA evaluation throughput vs TrackEval's HOTA metric class"
DESCRIPTION = """HOTA evaluation throughput against TrackEval's HOTA metric, timed in the same run.

Workload: by default the size of the WPAFB benchmark (--frames 512 frames of --objects 85 random-walk
objects, one prediction each with 3 px noise, 5 % under a wrong identity); --gt and --pred score given
MOTChallenge files instead, e.g. the output of torchtrack track --benchmark wpafb. Centre similarity with
a 10 px distance. Both give the same scores (checked to 1e-9). TrackEval is a test-only dependency
(pip install torchtrack-mtt[test]); without it only torchtrack's time is printed.

Example: torchtrack bench hota --frames 100
"""


def add_arguments(parser) -> None:
    parser.add_argument("--gt", type=Path, help="ground truth (MOTChallenge text) instead of the synthetic workload")
    parser.add_argument("--pred", type=Path, help="tracker output (MOTChallenge text), with --gt")
    parser.add_argument("--frames", type=positive_int, default=512, help="synthetic workload: frames (default 512)")
    parser.add_argument("--objects", type=positive_int, default=85, help="synthetic workload: objects per frame")
    parser.add_argument("--repeats", type=positive_int, default=3, help="timed repeats, best kept (default 3)")


def run(args) -> int:
    if (args.gt is None) != (args.pred is None):
        raise TorchtrackError("--gt and --pred go together")
    gt, pred = (read_mot(args.gt), read_mot(args.pred)) if args.gt is not None else (None, None)
    result = hota.measure(gt, pred, args.frames, args.objects, args.repeats, args.seed)
    text = format_result(result)
    if result.extra.get("reference_prepare_seconds") is not None:
        text += (f"\nTrackEval's preparation of the similarities (not timed above): "
                 f"{result.extra['reference_prepare_seconds']:.3f} s; ratio including it "
                 f"{result.extra['ratio_with_preparation']:.1f}x; scores agree: {result.extra['scores_agree']}")
    return report(args, result, text)
