"""Motion and measurement models."""

from torchtrack.models.measurement import (
    LinearMeasurement,
    LinearPosition,
    MeasurementModel,
    RangeBearing,
    RelativePosition,
    wrap_angle,
)
from torchtrack.models.motion import (
    ConstantAcceleration,
    ConstantPosition,
    ConstantVelocity,
    CoordinatedTurn,
    CoordinatedTurnRate,
    LinearMotion,
    ModeControlInput,
    MotionModel,
)

__all__ = [
    "ConstantAcceleration", "ConstantPosition", "ConstantVelocity", "CoordinatedTurn", "CoordinatedTurnRate",
    "LinearMeasurement", "LinearMotion", "LinearPosition", "MeasurementModel", "ModeControlInput", "MotionModel",
    "RangeBearing", "RelativePosition", "wrap_angle",
]
