"""``torchtrack eval-detector``: precision, recall, F1 and velocity error of the detector."""

from __future__ import annotations

from pathlib import Path

from torchtrack.cli._common import VIDEO_PRESETS, add_common_options, bounded, config_file, positive_float, positive_int
from torchtrack.cli._labelled import add_labelled_options, check_labelled_options, load_labelled
from torchtrack.detector.evaluate import PRIORS
from torchtrack.detector.inference import BACKENDS
from torchtrack.io.outputs import write_json
from torchtrack.metrics.table import format_table

NAME = "eval-detector"
HELP = "score the detector on held-out synthetic sequences and on the real WPAFB frames"
DESCRIPTION = HELP + """

A detection is a true positive when it is matched one-to-one (Hungarian) to a truth point within
--radius px (default 10). velocity_error_px: mean |v_pred - v_true| (px/frame) over matched
detections. fps: detector calls per second (pre-processing, network, decoding) at the frames' size,
wall clock; fps_cpu_time: the same from the process CPU time (what an unloaded machine gives).
Held-out sequences use seeds never used in training (split 'test'). A detector trained on registered
pairs (data.register in its config, as the shipped one) sees the previous frame warped onto the
current one by the true camera motion, as after the pipeline's registration, and its velocity is
scored against the velocity over the ground. The 'moving vehicles' row scores the detections
predicted to move over the ground (for an unregistered detector: its velocity less the camera
jitter's image motion) at 2 px/frame or more against the moving truth (parked vehicles don't-care,
frames after the first). The WPAFB part runs where the WPAFB AOI 02 data
set is found (data/wpafb-aoi02, $TORCHTRACK_WPAFB or ../shared/data/wpafb-aoi02; torchtrack data fetch
wpafb gets it): all vehicles, and moving vehicles with detections on parked vehicles as don't-care.
Example: torchtrack eval-detector --sequences 4 --frames 20 --json out/eval.json

--images DIR with --gt or --truth-csv scores those labelled frames instead (only them), as a stream
registered as the pipeline registers (finetune.registration of the weights' config), with the same
two rows; --region X0 Y0 X1 Y1 counts only what lies inside (truth outside is don't-care, unmatched
detections outside are no false positives). JSON: images: {all: {...}, moving: {...}}, region.
Example: torchtrack eval-detector --images data/wpafb-aoi02/frames \\
  --truth-csv data/wpafb-aoi02/transformed_object_states.csv --region 300 0 585 496
"""

COLUMNS = ("precision", "recall", "f1", "velocity_error_px", "frames", "fps")  # of each row, and the JSON's top level


def add_arguments(parser) -> None:
    parser.add_argument("--weights", type=Path, default=None, help="checkpoint (default: shipped weights)")
    parser.add_argument("--config", type=config_file(*VIDEO_PRESETS), default=None,
                        help="video config of the held-out sequences (default: the checkpoint's training data)")
    parser.add_argument("--sequences", type=positive_int, default=4, help="held-out synthetic sequences (default 4)")
    parser.add_argument("--frames", type=bounded(int, ge=2), default=20, help="frames per sequence (default 20)")
    parser.add_argument("--radius", type=positive_float, default=10.0, help="match distance in px (default 10)")
    parser.add_argument("--threshold", type=bounded(float, ge=0, lt=1), default=None,
                        help="score threshold (default: checkpoint's)")
    parser.add_argument("--wpafb", type=Path, default=None, help="WPAFB AOI 02 folder (default: the located data set, "
                        "see torchtrack data --help; skipped where there is none)")
    parser.add_argument("--no-wpafb", action="store_true", help="skip the real frames")
    parser.add_argument("--prior", choices=PRIORS, default="stream",
                        help="prior heatmap of each synthetic frame after the first: the previous detections "
                             "(stream, default: as in use), the previous truth (truth: a perfect feedback) or "
                             "none (empty); velocities are continued only with stream; the real frames always "
                             "stream")
    add_labelled_options(parser, "to score instead of the synthetic sequences and the WPAFB frames")
    parser.add_argument("--backend", choices=BACKENDS, default="float",
                        help="the network in float (default) or int8 on the CPU (needs the checkpoint's int8 "
                             "calibration: the shipped weights have one, torchtrack quantize-detector adds one); "
                             "auto: int8 where calibrated, else float")
    parser.add_argument("--threads", type=positive_int, default=1,
                        help="torch intra-op threads (default 1: fastest when other processes load the CPU)")
    add_common_options(parser)


def wpafb_path(given: Path | None) -> tuple[Path | None, str | None]:
    """``(folder, None)`` of the WPAFB data (``--wpafb`` or the located one), or ``(None, why)`` where
    no folder was given and none is found; a given folder without the truth is an error."""
    from torchtrack.errors import TorchtrackError
    from torchtrack.io.datasets import WPAFB, wpafb_folder

    if given is not None:
        if not (given / WPAFB.marker).is_file():
            raise TorchtrackError(f"--wpafb {given}: no {WPAFB.marker} there")
        return given, None
    try:
        return wpafb_folder(), None
    except TorchtrackError as exc:
        return None, str(exc)


def run(args) -> int:

    from torchtrack.detector.dataset import split_seed
    from torchtrack.detector.evaluate import evaluate_synthetic
    from torchtrack.detector.wpafb import evaluate_wpafb
    from torchtrack.sim.video_config import from_dict, load_video_config
    from torchtrack.threads import torch_threads

    check_labelled_options(args)
    if args.images is not None:
        return _score_images(args)
    path, absent = (None, None) if args.no_wpafb else wpafb_path(args.wpafb)
    with torch_threads(args.threads):
        det = _detector(args)
        video = load_video_config(args.config) if args.config else from_dict(dict(det.config.data.video))
        seeds = [split_seed(args.seed, "test", i) for i in range(args.sequences)]
        result = evaluate_synthetic(det, video.replace(frames=args.frames), seeds, args.radius, prior=args.prior)
        real = evaluate_wpafb(det, path, args.radius) if path is not None else None
    scored = {"synthetic (held out)": result, "synthetic, moving vehicles": result["moving"]}
    payload = {**{k: result[k] for k in (*COLUMNS, "fps_cpu_time")}, "backend": det.backend,
               "synthetic": {**result, "prior": args.prior}}
    if real is not None:
        payload["wpafb"] = real
        scored.update({f"WPAFB real, {name} vehicles": real[name] for name in ("all", "moving")})
    elif not args.no_wpafb:
        print(f"(real frames skipped: {absent})")
    rows = [[name, *(r[k] for k in COLUMNS)] for name, r in scored.items()]
    print(format_table(["data", "precision", "recall", "F1", "vel err px/fr", "frames", "fps"], rows))
    write_json(args.json, payload)
    return 0


def _detector(args):
    """The detector of ``--weights`` with ``--threshold`` where given."""
    import dataclasses

    from torchtrack.detector.inference import load_detector

    det = load_detector(args.weights, backend=args.backend)
    if args.threshold is not None:
        det.config = dataclasses.replace(det.config, decode=dataclasses.replace(det.config.decode,
                                                                                 threshold=args.threshold))
    return det


def _score_images(args) -> int:
    from torchtrack.detector.labelled import evaluate_labelled
    from torchtrack.threads import torch_threads

    with torch_threads(args.threads):
        det = _detector(args)
        data, region = load_labelled(args, det.config.finetune.registration)
        scores = evaluate_labelled(det, data, region, args.radius)
    rows = [[f"images, {name} vehicles", *(scores[name][k] for k in COLUMNS)] for name in ("all", "moving")]
    print(format_table(["data", "precision", "recall", "F1", "vel err px/fr", "frames", "fps"], rows))
    write_json(args.json, {"images": scores, "region": list(region)})
    return 0
