"""Evaluation metrics: OSPA and GOSPA on point sets, CLEAR-MOT / MT-PT-ML / IDF1 on MOTChallenge tracks."""

from torchtrack.metrics.clear_mot import clear_mot
from torchtrack.metrics.ospa import GOSPAResult, OSPAResult, gospa, ospa

__all__ = ["GOSPAResult", "OSPAResult", "clear_mot", "gospa", "ospa"]
