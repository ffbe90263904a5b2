"""``torchtrack quantize-detector``: add an int8 calibration to a detector checkpoint."""

from __future__ import annotations

from pathlib import Path

from torchtrack.cli._common import add_common_options, positive_int
from torchtrack.io.outputs import write_json

NAME = "quantize-detector"
HELP = "calibrate a detector checkpoint for int8 inference on the CPU (the float weights unchanged)"
DESCRIPTION = HELP + """

Streams the float network over synthetic sequences of the training split (generator seeds never used for
held-out scores) at the checkpoint's training frame size, observes the range of every activation that the
int8 network quantises, and writes the checkpoint with that table (and the digest of the weights it belongs
to) to --out. load_detector(path, backend="int8") then runs the network in int8 on the CPU;
eval-detector --backend float|int8 scores either. A checkpoint whose weights change afterwards
(fine-tuning) runs in float until it is calibrated again.
Example: torchtrack quantize-detector --weights out/detector-train/best.pt --out weights.pt
"""


def add_arguments(parser) -> None:
    parser.add_argument("--weights", type=Path, default=None, help="checkpoint (default: the shipped weights)")
    parser.add_argument("--out", type=Path, required=True, help="checkpoint to write (may be --weights)")
    parser.add_argument("--sequences", type=positive_int, default=4, help="calibration sequences (default 4)")
    parser.add_argument("--frames", type=positive_int, default=10, help="frames per sequence (default 10)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch intra-op threads (default 1)")
    add_common_options(parser)


def run(args) -> int:
    from torchtrack.detector.calibration import calibrated_checkpoint
    from torchtrack.detector.inference import DEFAULT_WEIGHTS
    from torchtrack.threads import torch_threads

    with torch_threads(args.threads):
        entry = calibrated_checkpoint(args.weights or DEFAULT_WEIGHTS, args.out, args.sequences, args.frames,
                                      args.seed)
    print(f"{args.out}: int8 calibration of {len(entry['table'])} activations from "
          f"{entry['calibration']['inputs']} network inputs")
    write_json(args.json, entry["calibration"] | {"points": len(entry["table"])})
    return 0
