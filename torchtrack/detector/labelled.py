"""Labelled real frames: a folder of images with point truth, as training pairs and as a scored stream.

Frame ``k`` (from 1) of the folder (natural-sort order, :class:`torchtrack.io.frames.FolderSource`) is
truth frame ``k`` (MOTChallenge ``gt.txt``, or the WPAFB CSV renumbered from its first row). Per frame:
the truth points, their velocities ``x_k - x_{k-1}`` where the truth links the previous frame, and
whether each vehicle is *moving* — more than 5 px from its frame-``k`` position at some frame of
``k..k+15`` (the rule of :mod:`torchtrack.detector.wpafb`; truth beyond the last image counts). A frame
byte-identical to its predecessor (WPAFB frames 100 and 101) is *repeated*: the pair shows no motion,
so it has no velocity targets and is not scored for motion. With ``motions`` (per frame the camera map
current -> previous, as the pipeline's registration estimates it) a registered detector sees the
previous frame warped onto the current one and velocities over the ground, as in the pipeline.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from torchtrack.detector.dataset import SequenceCache
from torchtrack.detector.evaluate import Scores, ground_velocity, moving_only, stream
from torchtrack.detector.region import Region
from torchtrack.errors import TorchtrackError
from torchtrack.io.frames import FolderSource
from torchtrack.io.mot import MOTData
from torchtrack.io.moving import MOVING_DISPLACEMENT, MOVING_WINDOW


class LabelledFrames(NamedTuple):
    """frames (T, H, W) uint8; per frame ``k`` (0-based) ``ids[k]`` (N,), ``xy[k]`` (N, 2) px (x, y),
    ``velocity[k]`` (N, 2) px/frame image motion (NaN: not linked, or a repeated frame), ``moving[k]`` (N,)
    bool; ``repeated`` (T,) bool; ``motions[k]`` (3, 3) camera map current -> previous (identity for k = 0)."""

    frames: np.ndarray
    ids: list[np.ndarray]
    xy: list[np.ndarray]
    velocity: list[np.ndarray]
    moving: list[np.ndarray]
    repeated: np.ndarray
    motions: list[np.ndarray]

    def as_cache(self) -> SequenceCache:
        """One sequence as a :class:`SequenceCache` (its homographies reference -> frame composed from
        the motions, ``H_k = M_k^{-1} H_{k-1}``), for :class:`~torchtrack.detector.dataset.PairDataset`."""
        homs = [np.eye(3)]
        for m in self.motions[1:]:
            homs.append(np.linalg.inv(m) @ homs[-1])
        start = np.concatenate([[0], np.cumsum([len(i) for i in self.ids])])
        return SequenceCache(torch.from_numpy(self.frames[None]), torch.from_numpy(start),
                             torch.from_numpy(np.concatenate(self.ids)),
                             torch.from_numpy(np.concatenate(self.xy)).float(),
                             torch.from_numpy(np.concatenate(self.velocity)).float(),
                             torch.from_numpy(np.stack(homs)[None]))


def read_images(folder: str | Path) -> np.ndarray:
    """The grey frames of ``folder`` as (T, H, W) uint8; fewer than two is an error naming the folder."""
    frames = np.stack([f.image for f in FolderSource(folder)])
    if len(frames) < 2:
        raise TorchtrackError(f"--images {folder}: needs at least two frames (pairs of current and previous)")
    return frames


def _link(ids: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``ids`` and ``other`` of the objects with the same id; unlabelled ids (< 0) never link."""
    _, here, there = np.intersect1d(ids, other, return_indices=True)
    known = ids[here] >= 0
    return here[known], there[known]


def label_frames(frames: np.ndarray, truth: MOTData, source: str,
                 motions: list[np.ndarray] | None = None) -> LabelledFrames:
    """Attach ``truth`` (frames from 1) to ``frames`` (T, H, W); ``source`` names the truth file in errors
    (a point outside the frames is refused). ``motions``: per frame current -> previous (default identity)."""
    t, h, w = frames.shape
    by_frame = {int(k): idx for k, idx in zip(truth.frames(), truth.split())}
    centres = truth.centers()
    none = np.zeros(0, int)

    def at(k: int) -> tuple[np.ndarray, np.ndarray]:
        idx = by_frame.get(k, none)
        return truth.id[idx].astype(np.int64), centres[idx].astype(np.float64)

    ids, xy, velocity, moving = [], [], [], []
    repeated = np.array([k > 0 and np.array_equal(frames[k], frames[k - 1]) for k in range(t)])
    for k in range(1, t + 1):
        i, p = at(k)
        outside = (p[:, 0] < 0) | (p[:, 0] > w - 1) | (p[:, 1] < 0) | (p[:, 1] > h - 1)
        if outside.any():
            j = int(np.argmax(outside))
            raise TorchtrackError(f"{source}: frame {k}, object {i[j]} at ({p[j, 0]:.1f}, {p[j, 1]:.1f}) lies "
                                  f"outside the {w} x {h} frames")
        pi, pp = at(k - 1)
        v = np.full_like(p, np.nan)
        if not repeated[k - 1]:
            here, there = _link(i, pi)
            v[here] = p[here] - pp[there]
        disp = np.zeros(len(i))
        for j in range(k + 1, k + MOVING_WINDOW + 1):
            li, lp = at(j)
            here, there = _link(i, li)
            disp[here] = np.maximum(disp[here], np.linalg.norm(lp[there] - p[here], axis=1))
        ids.append(i)
        xy.append(p)
        velocity.append(v)
        moving.append(disp > MOVING_DISPLACEMENT)
    motions = [np.eye(3)] * t if motions is None else [np.eye(3)] + [np.asarray(m) for m in motions[1:]]
    return LabelledFrames(frames, ids, xy, velocity, moving, repeated, motions)


@torch.inference_mode()
def evaluate_labelled(detector, data: LabelledFrames, region: Region | None = None, radius: float = 10.0,
                      min_speed: float = 2.0) -> dict:
    """``{"all": scores, "moving": scores}`` of ``detector`` streamed over ``data`` (the prior of each
    frame the previous detections), counting only what lies inside ``region`` (default: everywhere):
    truth outside is don't-care and unmatched detections outside are no false positives. *moving*:
    detections predicted to move at ``min_speed`` px/frame or more against the moving truth (the rest
    don't-care), on frames after the first that are not repeated. A registered detector
    (``data.register``) gets the previous frame warped by ``data.motions`` and is scored against
    velocities over the ground."""
    t, h, w = data.frames.shape
    region = region or Region(0, 0, w, h)
    registered = bool(detector.config.data.register)
    all_s, mov_s = Scores(radius), Scores(radius)
    dets = stream(detector, list(data.frames), all_s, data.motions if registered else None)
    for k, det in enumerate(dets):
        xy, vel = data.xy[k], data.velocity[k]
        if registered and k > 0:
            vel = ground_velocity(xy, vel, data.motions[k])
        inside = region.contains(xy)
        all_s.add(det, xy, vel if k > 0 else None, care=inside, counted=region.contains(det.xy.numpy()))
        if k > 0 and not data.repeated[k]:
            fast = moving_only(det, min_speed)
            mov_s.add(fast, xy, vel, care=data.moving[k] & inside, counted=region.contains(fast.xy.numpy()))
    mov_s.seconds, mov_s.cpu_seconds = all_s.seconds, all_s.cpu_seconds
    return {"all": all_s.result(), "moving": mov_s.result()}
