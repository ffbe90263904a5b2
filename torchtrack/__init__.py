"""torchtrack: batched, differentiable target tracking on PyTorch."""

from torchtrack.errors import TorchtrackError

__version__ = "0.1.0"
__all__ = ["TorchtrackError", "__version__"]
