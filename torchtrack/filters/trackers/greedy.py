"""CenterTrack's tracking step (Zhou, Koltun & Krähenbühl, "Tracking objects as points", ECCV 2020) behind the
interface of :mod:`torchtrack.filters.trackers.protocol`: each detection, displaced back by its own velocity, greedily
takes the nearest unmatched track of the previous frame."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor

from torchtrack.association.pairs import gated_pairs
from torchtrack.filters.trackers.options import GreedyConfig, tracker_config
from torchtrack.filters.trackers.protocol import as_points, frame_step


def greedy(config: GreedyConfig | Mapping | None = None) -> GreedyTracker:
    """The greedy tracker from its configuration (or the mapping of the keys to change)."""
    return GreedyTracker(tracker_config("greedy", config))


class GreedyTracker:
    """CenterTrack-style greedy matching (Zhou et al. 2020, section 4.3).

    Each detection ``p`` with velocity ``v`` (px/frame; zero when the detector gives none) is displaced to
    ``p − v``, its position in the previous frame. Detections, in decreasing confidence (the input
    order), each take the nearest still-unmatched track of the previous frame within ``max_distance``
    and inherit its id; the others start new tracks. A track not matched for more than ``max_age``
    frames is forgotten (``max_age = 0``: CenterTrack's default, no memory). Every detection is
    reported. Options: :class:`~torchtrack.filters.tracker_config.GreedyConfig`. The matching is a k-d tree search
    on the host: detections on another device are copied there, the results returned on their device.
    """

    def __init__(self, options: GreedyConfig | None = None):
        self.options = options if options is not None else GreedyConfig()
        self.reset()

    def reset(self) -> None:
        self.pos = np.empty((0, 2))
        self.ids = np.empty(0, dtype=np.int64)
        self.age = np.empty(0, dtype=np.int64)
        self.next_id = 1
        self._last_frame: int | None = None

    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None) -> tuple[Tensor, Tensor]:
        frame_step(self._last_frame, frame)
        self._last_frame = frame
        positions = as_points(positions, torch.float64)
        p = positions.cpu().numpy()
        back = p - (as_points(velocities, torch.float64).cpu().numpy() if velocities is not None else 0.0)
        M, T = p.shape[0], self.pos.shape[0]
        ids = np.zeros(M, dtype=np.int64)
        taken = np.zeros(T, dtype=bool)
        if T and M:
            # each detection's candidates within the gate, nearest first (ties: the earlier track)
            di, tj, d = gated_pairs(back, self.pos, self.options.max_distance)
            order = np.lexsort((tj, d, di))
            for i, j in zip(di[order].tolist(), tj[order].tolist()):
                if not ids[i] and not taken[j]:          # detection i unmatched yet, track j free
                    taken[j] = True
                    ids[i] = self.ids[j]
        new = ids == 0
        ids[new] = np.arange(self.next_id, self.next_id + int(new.sum()))
        self.next_id += int(new.sum())
        age = self.age[~taken] + 1
        keep = age <= self.options.max_age
        self.pos = np.concatenate([p, self.pos[~taken][keep]])
        self.ids = np.concatenate([ids, self.ids[~taken][keep]])
        self.age = np.concatenate([np.zeros(M, dtype=np.int64), age[keep]])
        return torch.from_numpy(ids).to(positions.device), positions.clone()
