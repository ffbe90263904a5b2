"""Evaluation metrics: OSPA and GOSPA on point sets, CLEAR-MOT / MT-PT-ML / IDF1 and HOTA on MOTChallenge tracks."""

from torchtrack.metrics.clear_mot import clear_mot, drop_ignored
from torchtrack.metrics.hota import hota
from torchtrack.metrics.ospa import GOSPAResult, OSPAResult, gospa, mot_ospa_gospa, ospa

__all__ = ["GOSPAResult", "OSPAResult", "clear_mot", "drop_ignored", "gospa", "hota", "mot_ospa_gospa", "ospa"]
