"""The one exception type torchtrack raises for bad input."""


class TorchtrackError(ValueError):
    """Bad input or a failed numerical step; the message names the argument, file or step."""
