"""The common streaming interface of the multi-target trackers, and the factory that builds them.

A tracker is fed one frame at a time::

    tracker = make_tracker("gmphd", config)          # gmphd, labelled-gmphd, sort, greedy, pmb
    tracker.reset()
    ids, positions = tracker.step(frame, positions, velocities)   # (K, 2) tensors; velocities or None

``step`` returns the **confirmed** estimates of that frame: ``ids (E,)`` int64 (unique within a frame)
and ``positions (E, 2)`` in the detections' coordinates. ``frame`` is the frame number (increasing;
gaps are time steps without detections).

``config`` is the tracker's configuration dataclass (:mod:`torchtrack.filters.trackers.options`: type, default
and meaning of every option), a mapping of the keys to change from its defaults, or None. New trackers
register a factory ``config -> tracker`` here by module path (imported on first use) and their defaults in
:data:`torchtrack.filters.trackers.options.DEFAULTS`.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable
from typing import Any, Protocol

import torch
from torch import Tensor

from torchtrack.errors import TorchtrackError


class Tracker(Protocol):
    """What every tracker offers."""

    def reset(self) -> None: ...

    def step(self, frame: int, positions: Tensor, velocities: Tensor | None = None) -> tuple[Tensor, Tensor]: ...


TRACKERS: dict[str, str] = {
    "gmphd": "torchtrack.filters.gmphd.presets:enhanced_gmphd",
    "labelled-gmphd": "torchtrack.filters.gmphd.presets:labelled_gmphd",
    "sort": "torchtrack.filters.trackers.sort:sort",
    "greedy": "torchtrack.filters.trackers.greedy:greedy",
    "pmb": "torchtrack.filters.pmb.tracker:PMBTracker",
    "glmb": "torchtrack.filters.glmb.tracker:glmb",
}
"""Tracker name → ``module:factory`` taking the tracker's configuration (dataclass, mapping or None)."""


def frame_step(last_frame: int | None, frame: int) -> float:
    """Frames from ``last_frame`` to ``frame`` (1 for the first frame): the ``dt`` of a tracker's step; an error
    unless frames increase."""
    if last_frame is not None and frame <= last_frame:
        raise TorchtrackError(f"frames must increase: frame {frame} after {last_frame}")
    return 1.0 if last_frame is None else float(frame - last_frame)


def as_points(positions, dtype: torch.dtype) -> Tensor:
    """A tracker's input positions (any array of ``2K`` numbers) as a ``(K, 2)`` tensor of ``dtype``."""
    return torch.as_tensor(positions, dtype=dtype).reshape(-1, 2)


def tracker_names() -> list[str]:
    """Registered tracker names, in registration order."""
    return list(TRACKERS)


def make_tracker(name: str, config: Any = None) -> Tracker:
    """Build the tracker ``name`` from its configuration: its dataclass, a mapping of the keys to change from
    the built-in defaults, or None (the defaults)."""
    if name not in TRACKERS:
        raise TorchtrackError(f"unknown tracker {name!r}; choose one of {', '.join(TRACKERS)}")
    module, _, factory = TRACKERS[name].partition(":")
    tracker = getattr(importlib.import_module(module), factory)(config)
    tracker.reset()
    return tracker


def run_tracker(tracker: Tracker, frames: Iterable[tuple[int, Tensor, Tensor | None]]
                ) -> list[tuple[int, Tensor, Tensor]]:
    """Feed ``(frame, positions, velocities)`` triples through ``tracker``; returns ``(frame, ids, positions)``."""
    return [(frame, *tracker.step(frame, z, v)) for frame, z, v in frames]
