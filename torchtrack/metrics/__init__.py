"""Evaluation metrics: CLEAR-MOT / MT-PT-ML / IDF1 and HOTA on MOTChallenge tracks (NumPy), OSPA and GOSPA on
point sets (torch, differentiable: import them from :mod:`torchtrack.metrics.ospa`)."""

from torchtrack.metrics.clear_mot import clear_mot, drop_ignored
from torchtrack.metrics.hota import hota

__all__ = ["clear_mot", "drop_ignored", "hota"]
