"""Resident-memory growth of each per-frame step of the video pipeline on one synthetic S × S frame pair
(issue #28): the keyframe's and the next frame's registration, the warp of the previous frame, the detector,
the motion evidence and the grey levels. Per step: the peak of the process's resident set over its value
when the step starts (``VmHWM`` reset through ``/proc/self/clear_refs``) and what the step still holds after.

    MALLOC_MMAP_THRESHOLD_=131072 OMP_NUM_THREADS=1 python scripts/memory_steps.py 4096

(the malloc setting returns freed buffers to the system, so that each step's growth is its own and not hidden
by memory an earlier step freed; tracemalloc does not see torch's or OpenCV's buffers).
"""

import sys
from pathlib import Path

import numpy as np
import torch

from torchtrack.bench._memory import resident_kb
from torchtrack.detector import load_detector
from torchtrack.detector.dataset import split_seed
from torchtrack.geometry import warp_previous
from torchtrack.pipeline.detection import grey_level, motion_evidence
from torchtrack.pipeline.registration import Registration
from torchtrack.sim.video import generate_sequence
from torchtrack.sim.video_config import VideoConfig


def main(size: int) -> None:
    torch.set_num_threads(1)
    config = VideoConfig(height=size, width=size, frames=2)
    frames = [f.image for f in generate_sequence(config, torch.Generator().manual_seed(split_seed(0, "test", 1)))]
    detector = load_detector()
    detector.detect(frames[0][:512, :512], frames[0][:512, :512])     # first-call costs outside the steps
    rows = []

    def step(name, run):
        Path("/proc/self/clear_refs").write_text("5")
        base = resident_kb("VmRSS")
        out = run()
        rows.append((name, (resident_kb("VmHWM") - base) / 1024, (resident_kb("VmRSS") - base) / 1024))
        return out

    registration = Registration()
    step("registration, keyframe (corners)", lambda: registration(frames[0]))
    h = step("registration, next frame (LK flow)", lambda: registration(frames[1])).homography
    prev = step("warp of the previous frame", lambda: warp_previous(frames[0], h, frames[1].shape, fill=frames[1]))
    first = detector.detect(frames[0])
    found = step("detector (detect)", lambda: detector.detect(frames[1], prev, first.xy, prev_velocity=first.velocity))
    xy = found.xy.numpy().astype(np.float64)
    step("motion evidence", lambda: motion_evidence(frames[1], prev, xy))
    step("grey levels", lambda: grey_level(frames[1], xy))
    print(f"{size}² frame pair, {len(xy)} detections; MiB")
    print("| step | peak + | held after |\n| --- | --- | --- |")
    for name, peak, held in rows:
        print(f"| {name} | {peak:.0f} | {held:.0f} |")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 4096)
