"""What the multi-target trackers share: the streaming :class:`Tracker` protocol and its registry
(:func:`make_tracker`), the typed options of every tracker, and the SORT and greedy baselines."""

from torchtrack.filters.trackers.greedy import GreedyTracker
from torchtrack.filters.trackers.options import (
    GLMBConfig,
    GMPHDConfig,
    GreedyConfig,
    PMBConfig,
    SORTConfig,
    load_tracker_configs,
    tracker_config,
)
from torchtrack.filters.trackers.protocol import Tracker, make_tracker, run_tracker, tracker_names
from torchtrack.filters.trackers.sort import SORT

__all__ = [
    "GLMBConfig", "GMPHDConfig", "GreedyConfig", "GreedyTracker", "PMBConfig", "SORT", "SORTConfig", "Tracker",
    "load_tracker_configs", "make_tracker", "run_tracker", "tracker_config", "tracker_names",
]
