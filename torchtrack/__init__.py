"""torchtrack: batched, differentiable target tracking on PyTorch.

The main job from Python: :func:`track` runs a tracker on frames, a video or detections (as ``torchtrack track``;
calibrated first with ``calibrate=N``) and :func:`evaluate` scores tracks (as ``torchtrack eval``):
:func:`torchtrack.calibrated_track.track` and :func:`torchtrack.metrics.evaluation.evaluate_scores`, imported on
first use so ``import torchtrack`` stays light.
"""

from torchtrack.errors import TorchtrackError

__version__ = "0.1.0"
__all__ = ["TorchtrackError", "__version__", "evaluate", "track"]


def __getattr__(name: str):
    if name == "track":
        from torchtrack.calibrated_track import track

        return track
    if name == "TrackResult":
        from torchtrack.pipeline.api import TrackResult

        return TrackResult
    if name == "evaluate":
        from torchtrack.metrics.evaluation import evaluate_scores

        return evaluate_scores
    raise AttributeError(f"module 'torchtrack' has no attribute {name!r}")
