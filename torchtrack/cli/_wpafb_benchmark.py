"""The WPAFB real-data tracker benchmark behind ``torchtrack track --benchmark CONFIG``.

Real vehicle truth (WPAFB 2009, AOI 02) → simulated detections (p_D, σ, clutter, velocity noise) →
every tracker → CLEAR-MOT at the paper's 10 px, on all vehicles and on the moving ones (moved more than
5 px over the last 15 frames; the detector sees only those, as the paper's detector is trained on them).
"""

from __future__ import annotations

from pathlib import Path

import torch
import yaml

from torchtrack.cli._common import write_json
from torchtrack.cli.track import compare, load_tracker_config
from torchtrack.errors import TorchtrackError
from torchtrack.filters.multitarget import tracker_names
from torchtrack.io.datasets import WPAFB, wpafb_truth_csv

REPO = Path(__file__).resolve().parents[2]


def truth_csv(config: dict) -> Path:
    """The truth CSV that the config's ``truth`` names: ``wpafb`` (the default) for the data set wherever
    :func:`torchtrack.io.datasets.locate` finds it, or a path to the CSV or its folder."""
    return wpafb_truth_csv(config.get("truth", WPAFB.name))


def run_benchmark(config_path: Path, out: Path, seed: int, trackers: list[str] | None = None,
                  tracker_config_path: Path | None = None) -> dict:
    """Run the benchmark of ``config_path``; prints one table per subset, writes ``out/<subset>/...``."""
    from torchtrack.io.mot import write_motdata
    from torchtrack.io.wpafb import moving_mask, read_wpafb_csv
    from torchtrack.sim.detections import simulate_detections

    try:
        config = yaml.safe_load(Path(config_path).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise TorchtrackError(f"cannot read benchmark config {config_path}: {exc}") from None
    det_cfg = dict(config.get("detections") or {})
    mov_cfg = dict(config.get("moving") or {})
    threshold = float(config.get("threshold", 10.0))
    trackers = trackers or list(config.get("trackers") or tracker_names())
    tcfg_path = tracker_config_path or (REPO / config["tracker_config"] if config.get("tracker_config") else None)
    tracker_config = load_tracker_config(tcfg_path)
    truth = read_wpafb_csv(truth_csv(config))
    image_size = tuple(det_cfg.get("image_size", (585, 496)))
    payload = {"config": str(config_path), "seed": seed, "detections": det_cfg, "threshold": threshold,
               "subsets": {}}
    for subset in config.get("subsets", ["all", "moving"]):
        if subset == "all":
            gt = truth
        elif subset == "moving":
            gt = truth.select(moving_mask(truth, float(mov_cfg.get("min_displacement", 5.0)),
                                          int(mov_cfg.get("window", 15))))
        else:
            raise TorchtrackError(f"{config_path}: unknown subset {subset!r} (all, moving)")
        g = torch.Generator().manual_seed(seed)
        det = simulate_detections(gt, pd=float(det_cfg.get("pd", 0.9)), sigma=float(det_cfg.get("sigma", 1.0)),
                                  clutter=float(det_cfg.get("clutter", 30)), image_size=image_size,
                                  velocity_sigma=det_cfg.get("velocity_sigma", 1.0), generator=g).detections
        sub_out = Path(out) / subset
        write_motdata(sub_out / "gt.txt", gt)
        write_motdata(sub_out / "det.txt", det)
        results, table = compare(det, tracker_config, sub_out, gt, threshold, trackers)
        print(f"\nWPAFB AOI 02, {subset} vehicles ({len(set(gt.id.tolist()))} trajectories, {gt.size} boxes, "
              f"{det.size} detections; p_D {det_cfg.get('pd', 0.9)}, sigma {det_cfg.get('sigma', 1.0)} px, "
              f"clutter {det_cfg.get('clutter', 30)}/frame, velocity noise {det_cfg.get('velocity_sigma', 1.0)} "
              f"px/frame; CLEAR-MOT at {threshold:g} px)")
        print(table)
        payload["subsets"][subset] = results
    write_json(Path(out) / "benchmark.json", payload)
    return payload

