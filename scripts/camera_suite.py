"""Score detector weights on a set of cameras, as a user would: for each camera simulate a sequence
(`simulate-video`), track it (`track --frames`), score the tracks on the moving vehicles (`eval --moving`) and the
detector alone on held-out sequences of that camera (`eval-detector --config`, its moving-vehicle row).

Cameras: the default camera, the presets camera-soft, camera-small-dark and camera-harsh, the default camera
with other vehicle sizes (--scales), and --draw N
validation cameras drawn from the ranges of configs/detector.yaml (data.cameras) with seeds of their own
(never a training seed: those are below 10,000,000 · 3).

    python scripts/camera_suite.py --weights out/det.pt --out out/cameras --draw 6
    python scripts/camera_suite.py --out out/cameras-shipped            # the shipped weights

Writes OUT/CAMERA/{camera.yaml, seq/, track/}, OUT/results.json and prints one table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

from torchtrack.detector.config import load_config
from torchtrack.sim.cameras import draw_camera, ranges_from_dict
from torchtrack.sim.video_config import VideoConfig, load_video_config

PRESETS = ("video", "camera-soft", "camera-small-dark", "camera-harsh")
VALIDATION_SEED = 40_000_000


def cameras(draw: int, scales: list[float]) -> dict[str, VideoConfig]:
    """The preset cameras, the default camera with vehicles of each median length of ``scales`` (px) and ``draw``
    validation cameras (every knob drawn, none kept at the base camera)."""
    out = {name: load_video_config(_preset(name)) for name in PRESETS}
    for m in scales:
        out[f"length-{m:g}"] = VideoConfig(vehicle_length_median=m, vehicle_length=(max(2.0, 0.6 * m), 3.0 * m))
    ranges = dataclasses.replace(ranges_from_dict(load_config(_preset("detector")).data.cameras), base_share=0.0)
    for i in range(draw):
        out[f"val-{i}"] = draw_camera(ranges, VideoConfig(), np.random.default_rng(VALIDATION_SEED + i))
    return out


def _preset(name: str) -> Path:
    from torchtrack.config import preset_path

    return preset_path(name)


def _run(*args: str) -> None:
    cmd = [sys.executable, "-m", "torchtrack", *args]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stderr[-2000:]}")


def score(name: str, camera: VideoConfig, out: Path, weights: list[str], frames: int, seed: int,
          detector_sequences: int) -> dict:
    d = out / name
    d.mkdir(parents=True, exist_ok=True)
    cfg_path = d / "camera.yaml"
    cfg_path.write_text(yaml.safe_dump({"video": json.loads(json.dumps(dataclasses.asdict(camera)))}))
    _run("simulate-video", "--config", str(cfg_path), "--out", str(d / "seq"), "--frames", str(frames),
         "--seed", str(seed), "--no-progress", "--force")
    _run("track", "--frames", str(d / "seq/frames"), "--no-video", "--out", str(d / "track"), *weights)
    _run("eval", "--gt", str(d / "seq/gt.txt"), "--pred", str(d / "track/tracks.txt"), "--moving",
         "--json", str(d / "eval.json"))
    _run("eval-detector", "--config", str(cfg_path), "--sequences", str(detector_sequences), "--frames", "12",
         "--no-wpafb", "--json", str(d / "detector.json"), *weights)
    mota = json.loads((d / "eval.json").read_text())["MOTA"]
    det = json.loads((d / "detector.json").read_text())
    return {"camera": name, "MOTA": mota, "detector_moving_f1": det["synthetic"]["moving"]["f1"],
            "detector_f1": det["f1"]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", help="detector weights (default: the shipped ones)")
    p.add_argument("--out", required=True)
    p.add_argument("--draw", type=int, default=6, help="validation cameras drawn from the ranges")
    p.add_argument("--scales", type=float, nargs="*", default=[], help="median vehicle lengths (px) to add")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--seed", type=int, default=1, help="simulate-video seed of every camera's sequence")
    p.add_argument("--detector-sequences", type=int, default=2)
    p.add_argument("--only", nargs="*", help="camera names to run (default all)")
    a = p.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    out = Path(a.out)
    weights = ["--weights", a.weights] if a.weights else []
    rows = []
    for name, camera in cameras(a.draw, a.scales).items():
        if a.only and name not in a.only:
            continue
        rows.append(score(name, camera, out, weights, a.frames, a.seed, a.detector_sequences))
        r = rows[-1]
        print(f"{r['camera']:<20} MOTA {100 * r['MOTA']:6.2f} %   detector moving F1 {r['detector_moving_f1']:.3f}"
              f"   all F1 {r['detector_f1']:.3f}", flush=True)
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    mota = [r["MOTA"] for r in rows]
    print(f"{'mean':<20} MOTA {100 * np.mean(mota):6.2f} %   min {100 * np.min(mota):6.2f} %")


if __name__ == "__main__":
    main()
