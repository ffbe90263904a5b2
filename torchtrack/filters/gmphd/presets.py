"""The two GM-PHD trackers of Table 1 of Aguilar, Ortner & Zerubia (2023), as the registry builds them:

- :func:`enhanced_gmphd` — the proposed GM-PHD (label fix, velocity map, detector velocity);
- :func:`labelled_gmphd` — the plain labelled GM-PHD (labels, no fix, no velocity map, births at rest).
"""

from __future__ import annotations

from collections.abc import Mapping

from torchtrack.filters.gmphd.input_aware import InputAwareGMPHD
from torchtrack.filters.gmphd.tracker import GMPHDTracker
from torchtrack.filters.trackers.options import GMPHDConfig, tracker_config


def enhanced_gmphd(config: GMPHDConfig | Mapping | None = None) -> InputAwareGMPHD:
    """The enhanced GM-PHD of the paper (all of sections 2.2–2.4) from its configuration (or the mapping of the
    keys to change), following the input: each frame runs with the options for detections with velocities
    or for positions only (:attr:`GMPHDConfig.positions_only`; :mod:`torchtrack.filters.gmphd_input`)."""
    cfg = tracker_config("gmphd", config)
    return InputAwareGMPHD(GMPHDTracker.from_config(cfg),
                           GMPHDTracker.from_config(cfg.for_input(False)) if cfg.positions_only else None)


def labelled_gmphd(config: GMPHDConfig | Mapping | None = None) -> GMPHDTracker:
    """The labelled GM-PHD baseline: the preset :data:`~torchtrack.filters.tracker_config.LABELLED_GMPHD` (no
    label fix or extensions, no velocity map, births at rest, position-only update) with ``config``'s keys."""
    return GMPHDTracker.from_config(tracker_config("labelled-gmphd", config))
