"""``torchtrack track``: run a multi-target tracker on detections, write tracks and score them.

The detections path is :func:`track_detections`; every input kind feeds the same streaming interface
(:mod:`torchtrack.filters.multitarget`) one frame at a time through :func:`run_frames`.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import torch
import yaml

from torchtrack.cli._common import add_common_options, format_table, write_json
from torchtrack.errors import TorchtrackError
from torchtrack.filters.multitarget import Tracker, make_tracker, tracker_names
from torchtrack.pipeline.cli_options import add_frame_options, run_frame_inputs

NAME = "track"
HELP = "run a multi-target tracker (gmphd, labelled-gmphd, sort, greedy) on detections and score it"
DESCRIPTION = """Run a tracker on a MOTChallenge detection file, one frame at a time.

Writes DIR/tracks.txt (MOTChallenge, one line per reported target) and DIR/metrics.json (CLEAR-MOT
against --gt at --threshold px, plus the tracker's frames per second). With --compare every tracker
runs on the same detections (DIR/<tracker>/...) and the paper's Table 1 is printed. With
--benchmark CONFIG the WPAFB real-data benchmark of configs/wpafb-benchmark.yaml runs end to end.

Examples:
  torchtrack track --detections det.txt --tracker gmphd --gt gt.txt --out out/track
  torchtrack track --detections det.txt --gt gt.txt --compare --out out/compare
  torchtrack track --detections det.txt --gt gt.txt --params out/tune-gmphd/params.yaml
  torchtrack track --benchmark configs/wpafb-benchmark.yaml --out out/wpafb
"""

TABLE_HEADER = ["Method", "GT", "MT (%)", "PT (%)", "ML (%)", "FP", "FN", "IDS", "MOTA (%)", "MOTP", "FPS"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--detections", type=Path, metavar="DET", help="MOTChallenge detection file (id -1; "
                        "velocity vx, vy in columns 8-9 where the detector gives one)")
    parser.add_argument("--tracker", choices=tracker_names(), default="gmphd",
                        help="tracker (default gmphd: the enhanced GM-PHD)")
    parser.add_argument("--config", type=Path, default=None, metavar="YAML",
                        help="tracker options: a YAML mapping with one section per tracker name "
                             "(e.g. configs/gmphd.yaml); defaults are the built-in values")
    parser.add_argument("--params", type=Path, default=None, metavar="FITTED",
                        help="fitted GM-PHD parameters from torchtrack tune (OUT/params.yaml): the tracker is "
                             "built from the file's options with the fitted values, exactly the tuned tracker "
                             "(with --detections; --tracker must be the file's, not with --config)")
    parser.add_argument("--gt", type=Path, default=None, help="ground truth (MOTChallenge) to score against")
    parser.add_argument("--out", type=Path, default=Path("out/track"), help="output folder (default out/track)")
    parser.add_argument("--threshold", type=float, default=10.0, help="CLEAR-MOT centre distance in px "
                        "(default 10)")
    parser.add_argument("--compare", action="store_true", help="run every tracker and print the Table 1 "
                        "comparison")
    parser.add_argument("--trackers", nargs="+", choices=tracker_names(), default=None,
                        help="trackers for --compare / --benchmark (default: all)")
    parser.add_argument("--benchmark", type=Path, default=None, metavar="CONFIG",
                        help="run the WPAFB real-data benchmark described by CONFIG")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1: the per-frame "
                        "work is small, more threads only add overhead)")
    add_common_options(parser)
    add_frame_options(parser)


# --------------------------------------------------------------------------- configs
def load_tracker_config(path: Path | None) -> dict:
    """The tracker-options YAML: a mapping ``tracker name -> options`` (empty without a path)."""
    if path is None:
        return {}
    try:
        cfg = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise TorchtrackError(f"cannot read tracker config {path}: {exc}") from None
    if not isinstance(cfg, dict):
        raise TorchtrackError(f"tracker config {path} must be a mapping of tracker name to options")
    unknown = set(cfg) - set(tracker_names())
    if unknown:
        raise TorchtrackError(f"tracker config {path}: unknown tracker section(s) {sorted(unknown)}; "
                              f"known: {tracker_names()}")
    return cfg


# --------------------------------------------------------------------------- running
def detection_frames(det, frames: Iterable[int]) -> Iterator[tuple[int, torch.Tensor, torch.Tensor | None]]:
    """``(frame, positions (K, 2), velocities (K, 2) or None)`` for every frame in ``frames`` (frames
    without detections give ``K = 0``) from a :class:`~torchtrack.io.mot.MOTData` of detections."""
    centres = det.centers()
    vel = det.velocity()
    order = np.argsort(det.frame, kind="stable")
    fr = det.frame[order]
    for f in frames:
        lo, hi = np.searchsorted(fr, f, "left"), np.searchsorted(fr, f, "right")
        idx = order[lo:hi]
        z = torch.from_numpy(centres[idx])
        v = torch.from_numpy(vel[idx]) if vel is not None else None
        yield int(f), z, v


def run_frames(tracker: Tracker, frames: Iterable[tuple[int, torch.Tensor, torch.Tensor | None]],
               tracks_path: Path | None = None) -> tuple[dict, float, int]:
    """Feed frames through ``tracker``; write ``tracks_path``. Returns the tracks as arrays
    ``{frame, id, cx, cy}``, the seconds spent inside ``tracker.step`` and the number of frames."""
    from torchtrack.io.mot import MOTWriter

    out = {"frame": [], "id": [], "cx": [], "cy": []}
    seconds, n = 0.0, 0
    writer = MOTWriter(tracks_path) if tracks_path is not None else None
    try:
        for frame, z, v in frames:
            t0 = time.perf_counter()
            ids, pos = tracker.step(frame, z, v)
            seconds += time.perf_counter() - t0
            n += 1
            ids_np, pos_np = ids.cpu().numpy(), pos.detach().cpu().numpy().astype(np.float64)
            if writer is not None:
                writer.write_frame(frame, ids_np, pos_np[:, 0], pos_np[:, 1])
            out["frame"].append(np.full(ids_np.shape[0], frame, dtype=np.int64))
            out["id"].append(ids_np.astype(np.int64))
            out["cx"].append(pos_np[:, 0])
            out["cy"].append(pos_np[:, 1])
    finally:
        if writer is not None:
            writer.close()
    tracks = {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}
    return tracks, seconds, n


def frame_range(*datas) -> range:
    """All frame numbers from the first to the last frame present in any of ``datas`` (MOTData)."""
    frames = [d.frame for d in datas if d is not None and d.size]
    if not frames:
        return range(1, 1)
    allf = np.concatenate(frames)
    return range(int(allf.min()), int(allf.max()) + 1)


def score(gt, tracks: dict, threshold: float) -> dict:
    """CLEAR-MOT of ``tracks`` against ``gt`` (MOTData)."""
    from torchtrack.io.mot import from_points
    from torchtrack.metrics import clear_mot

    pred = from_points(tracks["frame"], tracks["id"], tracks["cx"], tracks["cy"])
    return clear_mot(gt, pred, threshold=threshold)


def track_detections(det, tracker_name: str, config: dict, out: Path, gt=None, threshold: float = 10.0,
                     tracker: Tracker | None = None) -> dict:
    """Run one tracker on detections ``det`` (MOTData); writes ``out/tracks.txt`` and ``out/metrics.json``.

    ``tracker`` (already built, e.g. :func:`fitted_tracker`) replaces the one ``tracker_name`` and
    ``config`` describe. Returns the metrics (CLEAR-MOT keys where ``gt`` is given) with ``tracker``,
    ``frames``, ``FPS`` and, for the GM-PHD trackers, ``cap_hits``.
    """
    if tracker is None:
        tracker = make_tracker(tracker_name, config.get(tracker_name))
    frames = frame_range(det, gt)
    tracks, seconds, n = run_frames(tracker, detection_frames(det, frames), out / "tracks.txt")
    metrics = score(gt, tracks, threshold) if gt is not None else {}
    metrics = {"tracker": tracker_name, **metrics, "frames_run": n, "seconds": seconds,
               "FPS": n / seconds if seconds > 0 else float("inf")}
    if hasattr(tracker, "cap_hits"):
        metrics["cap_hits"] = tracker.cap_hits
    write_json(out / "metrics.json", metrics)
    return metrics


def fitted_tracker(args: argparse.Namespace) -> Tracker:
    """The GM-PHD tracker of a ``torchtrack tune`` fitted-parameter file (``--params``): built from the
    file's tracker options and loaded with the fitted values exactly (:func:`torchtrack.tune.load_filter`)."""
    from torchtrack.tune import load_filter
    from torchtrack.tuning.config import read_params_file

    doc = read_params_file(args.params, ("gmphd",), "torchtrack track --params")
    kind = (doc.get("model") or {}).get("tracker", "gmphd")
    if kind != args.tracker:
        raise TorchtrackError(f"{args.params}: fitted for --tracker {kind}; got --tracker {args.tracker}")
    given = {"--config": args.config, "--compare": args.compare, "--benchmark": args.benchmark,
             "--video/--frames/--sequences": args.video or args.frames or args.sequences}
    clash = [flag for flag, value in given.items() if value]
    if clash:
        raise TorchtrackError(f"--params sets the whole tracker and runs on --detections; it does not combine "
                              f"with {', '.join(clash)}")
    tracker = load_filter(args.params)
    tracker.reset()
    return tracker


def table_row(name: str, m: dict) -> list:
    """One row of the paper's Table 1 (MT/PT/ML as % of GT trajectories, MOTA in %)."""
    gt = m.get("GT", 0) or 0

    def pct(k):
        return 100.0 * m[k] / gt if gt else float("nan")

    return [name, int(gt), pct("MT"), pct("PT"), pct("ML"), int(m["FP"]), int(m["FN"]), int(m["IDS"]),
            100.0 * m["MOTA"], m["MOTP"], m["FPS"]]


def compare(det, config: dict, out: Path, gt, threshold: float, trackers: list[str]) -> tuple[dict, str]:
    """Every tracker in ``trackers`` on the same detections; returns per-tracker metrics and the table."""
    results, rows = {}, []
    for name in trackers:
        m = track_detections(det, name, config, out / name, gt, threshold)
        results[name] = m
        rows.append(table_row(name, m))
    return results, format_table(TABLE_HEADER, rows, floatfmt=".2f")


def run(args: argparse.Namespace) -> int:
    torch.set_num_threads(max(1, args.threads))
    torch.manual_seed(args.seed)
    fitted = fitted_tracker(args) if args.params is not None else None
    rc = run_frame_inputs(args, load_tracker_config(args.config).get(args.tracker))
    if rc is not None:
        return rc
    if args.benchmark is not None:
        from torchtrack.cli._wpafb_benchmark import run_benchmark

        payload = run_benchmark(args.benchmark, args.out, args.seed, args.trackers, args.config)
        write_json(args.json, payload)
        return 0
    if args.detections is None:
        raise TorchtrackError("give --detections DET (or --benchmark CONFIG)")
    from torchtrack.io.mot import read_mot

    config = load_tracker_config(args.config)
    det = read_mot(args.detections)
    gt = read_mot(args.gt) if args.gt is not None else None
    if args.compare:
        if gt is None:
            raise TorchtrackError("--compare needs --gt to score the trackers")
        results, table = compare(det, config, args.out, gt, args.threshold, args.trackers or tracker_names())
        print(table)
        write_json(args.out / "comparison.json", results)
        write_json(args.json, results)
        return 0
    m = track_detections(det, args.tracker, config, args.out, gt, args.threshold, fitted)
    if gt is not None:
        print(format_table(TABLE_HEADER, [table_row(args.tracker, m)], floatfmt=".2f"))
    else:
        print(f"{args.tracker}: {m['frames_run']} frames, {m['FPS']:.1f} frames/s; tracks in {args.out / 'tracks.txt'}")
    write_json(args.json, m)
    return 0
