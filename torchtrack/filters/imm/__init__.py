"""The interacting multiple model filter (batched, any state layout), its structured constant-velocity fast path,
and the class-conditioned IMM bank."""

from torchtrack.filters.imm.bank import BankState, BankUpdateInfo, ClassConditionedIMM
from torchtrack.filters.imm.cv import ConstantVelocityIMM
from torchtrack.filters.imm.filter import IMMResult, IMMState, IMMUpdateInfo, InteractingMultipleModel

__all__ = [
    "BankState", "BankUpdateInfo", "ClassConditionedIMM", "ConstantVelocityIMM", "IMMResult", "IMMState",
    "IMMUpdateInfo", "InteractingMultipleModel",
]
