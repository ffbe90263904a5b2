"""A small CenterTrack-style detector (Zhou, Koltun & Krähenbühl 2020) that trains on a CPU.

Public API::

    from torchtrack.detector import load_detector
    det = load_detector()                       # shipped weights, eval mode
    out = det.detect(frame, prev_frame, prev_points)
    out.xy, out.score, out.velocity             # (K, 2) px, (K,), (K, 2) px/frame (x_k - x_{k-1})
"""

from torchtrack.detector.config import DetectorConfig, load_config
from torchtrack.detector.decode import Detections, decode
from torchtrack.detector.inference import DEFAULT_WEIGHTS, Detector, load_detector
from torchtrack.detector.network import CenterTrackNet

__all__ = ["CenterTrackNet", "DEFAULT_WEIGHTS", "Detections", "Detector", "DetectorConfig", "decode",
           "load_config", "load_detector"]
