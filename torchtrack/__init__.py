"""torchtrack: batched, differentiable target tracking on PyTorch.

The main job from Python: :func:`track` runs a tracker on frames, a video or detections (as ``torchtrack track``)
and :func:`evaluate` scores tracks (as ``torchtrack eval``); both live in :mod:`torchtrack.pipeline.api` and are
imported on first use, so ``import torchtrack`` stays light.
"""

from torchtrack.errors import TorchtrackError

__version__ = "0.1.0"
__all__ = ["TorchtrackError", "__version__", "evaluate", "track"]


def __getattr__(name: str):
    if name in ("track", "evaluate", "TrackResult"):
        from torchtrack.pipeline import api

        return getattr(api, name)
    raise AttributeError(f"module 'torchtrack' has no attribute {name!r}")
