"""The δ-GLMB filter with joint prediction–update and Gibbs truncation, its adaptive birth, and its tracker."""

from torchtrack.filters.glmb.filter import Births, GLMBFilter, GLMBState, StepInfo
from torchtrack.filters.glmb.tracker import GLMBTracker, glmb

__all__ = ["Births", "GLMBFilter", "GLMBState", "GLMBTracker", "StepInfo", "glmb"]
