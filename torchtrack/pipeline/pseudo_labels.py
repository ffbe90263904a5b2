"""Pseudo-labels for adapting the detector to a video without truth: the tracks the pipeline is confident in.

A single frame's peak may be clutter; an identity the tracker confirmed and the fixed-lag output kept over
``min_length`` frames or more (:class:`~torchtrack.pipeline.fixed_lag.FixedLagTracks`: backfilled, gaps
filled, coasting tails trimmed) moved like a vehicle over all of them, in the registered frame. Those
positions become the truth of :func:`torchtrack.detector.labelled.label_frames` (velocities linked frame to
frame by identity, camera motion from the pipeline's homographies), shorter tracks are left out. What the
detector found that no confident track explains stays unsure: the fine-tune masks its neighbourhood out of the
loss (``finetune.unlabelled_static: dont_care``, :mod:`torchtrack.detector.unlabelled`), so that it is
neither taught as a vehicle nor as background.
"""

from __future__ import annotations

import numpy as np

from torchtrack.detector.labelled import LabelledFrames, label_frames
from torchtrack.io.mot import MOTData


def confident_tracks(tracks: MOTData, min_length: int) -> MOTData:
    """The rows of ``tracks`` whose identity is reported on at least ``min_length`` frames."""
    ids, counts = np.unique(tracks.id, return_counts=True)
    return tracks.select(np.isin(tracks.id, ids[counts >= min_length]))


def frame_motions(homographies: list[np.ndarray]) -> list[np.ndarray]:
    """Per frame the camera map current -> previous, ``H_{k-1}^{-1} H_k`` from the pipeline's frame -> reference
    homographies ``H_k`` (identity for the first frame)."""
    return [np.eye(3)] + [np.linalg.solve(a, b) for a, b in zip(homographies[:-1], homographies[1:])]


def pseudo_labels(frames: np.ndarray, tracks: MOTData, homographies: list[np.ndarray],
                  min_length: int) -> LabelledFrames:
    """``frames (T, H, W)`` labelled with the confident ``tracks`` (frame coordinates, frames from 1) of a
    pipeline run, whose per-frame homographies (frame -> reference) are ``homographies``."""
    h, w = frames.shape[1:]
    confident = confident_tracks(tracks, min_length)
    c = confident.centers()
    inside = (c[:, 0] >= 0) & (c[:, 0] <= w - 1) & (c[:, 1] >= 0) & (c[:, 1] <= h - 1)
    return label_frames(frames, confident.select(inside), "pseudo-labels", frame_motions(homographies))
