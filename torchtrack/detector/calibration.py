"""Calibrating a detector checkpoint for int8 inference (``torchtrack quantize-detector``): the table of
:func:`torchtrack.detector.quantized.calibrate` written into the checkpoint with the digest of its weights."""

from __future__ import annotations

import torch

from torchtrack.detector.checkpoint import load_checkpoint, save_checkpoint
from torchtrack.detector.dataset import sequence_camera, split_seed
from torchtrack.detector.inference import detector_from_checkpoint
from torchtrack.detector.quantized import ENGINE, calibrate, calibration_inputs, weights_digest
from torchtrack.sim.video_config import from_dict


def calibrated_checkpoint(path, out, sequences: int = 4, frames: int = 10, seed: int = 0) -> dict:
    """Add an int8 calibration to the detector checkpoint at ``path`` and write it to ``out`` (atomically; the
    float weights unchanged). Calibrated on ``sequences`` synthetic sequences of ``frames`` frames from the
    training split of generator seeds (never the held-out test split), each of the camera the training data
    gave that seed (the checkpoint's training video config, or one drawn from its ``data.cameras``), streamed
    through the float network. Returns the entry written under ``"int8"``."""
    data = load_checkpoint(path)
    det = detector_from_checkpoint(data, backend="float")
    video = from_dict(dict(det.config.data.video)).replace(frames=frames)
    seeds = [split_seed(seed, "train", i) for i in range(sequences)]
    inputs = [x for s in seeds for x in calibration_inputs(det, sequence_camera(det.config, video, s), [s])]
    entry = {"table": calibrate(det.net, inputs), "weights": weights_digest(data["model"]), "engine": ENGINE,
             "calibration": {"split": "train", "seed": seed, "sequences": sequences, "frames": frames,
                             "inputs": len(inputs)}}
    raw = torch.load(path, map_location="cpu", weights_only=True)   # as stored (validated above)
    save_checkpoint(out, {**{k: v for k, v in raw.items() if k not in ("format", "version")}, "int8": entry})
    return entry
