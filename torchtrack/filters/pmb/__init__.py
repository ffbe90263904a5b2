"""The Poisson multi-Bernoulli (TOMB/P) filter, its tracker, and tracking from a sensor of uncertain state."""

from torchtrack.filters.pmb.filter import Estimates, PMBFilter, PMBState, PMBUpdateInfo
from torchtrack.filters.pmb.sensor import JointSensorPMB, SensorState
from torchtrack.filters.pmb.tracker import PMBTracker

__all__ = ["Estimates", "JointSensorPMB", "PMBFilter", "PMBState", "PMBTracker", "PMBUpdateInfo", "SensorState"]
