"""Motion and measurement models."""

from torchtrack.models.measurement import (
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
    ModeControlInput,
    MotionModel,
)

__all__ = [
    "ConstantAcceleration", "ConstantPosition", "ConstantVelocity", "CoordinatedTurn", "CoordinatedTurnRate",
    "LinearPosition", "MeasurementModel", "ModeControlInput", "MotionModel", "RangeBearing", "RelativePosition",
    "wrap_angle",
]
