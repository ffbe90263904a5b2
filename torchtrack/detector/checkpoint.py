"""Checkpoints: one format for training (``last.pt``) and the shipped weights, read with
``torch.load(..., weights_only=True)`` and validated, so that a truncated or foreign file is a clear error.

Content: ``format`` (``"torchtrack-detector"``), ``version``, ``config`` (the :class:`DetectorConfig`
as a dict), ``model`` (state dict), and for training checkpoints ``epoch``, ``optimizer``, ``history``.
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchtrack.detector.config import config_from_dict
from torchtrack.errors import TorchtrackError
from torchtrack.io.outputs import atomic_file

FORMAT = "torchtrack-detector"
VERSION = 1


def save_checkpoint(path: str | Path, payload: dict) -> None:
    """Write ``payload`` (plus format and version) atomically (:func:`~torchtrack.io.outputs.atomic_file`)."""
    with atomic_file(path) as tmp:
        torch.save({"format": FORMAT, "version": VERSION, **payload}, tmp)


def load_checkpoint(path: str | Path) -> dict:
    """Read and validate a detector checkpoint; raise :class:`TorchtrackError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise TorchtrackError(f"detector checkpoint {path}: no such file")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise TorchtrackError(f"detector checkpoint {path}: unreadable, truncated or not a torch file "
                              f"({type(exc).__name__}: {(str(exc).splitlines() or [''])[0][:120]})") from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise TorchtrackError(f"detector checkpoint {path}: not a torchtrack detector checkpoint "
                              f"(no 'format': '{FORMAT}' entry)")
    if data.get("version") != VERSION:
        raise TorchtrackError(f"detector checkpoint {path}: version {data.get('version')}, expected {VERSION}")
    for key in ("config", "model"):
        if key not in data:
            raise TorchtrackError(f"detector checkpoint {path}: missing '{key}'")
    data["config"] = config_from_dict(data["config"], f"detector checkpoint {path}")
    model = data["model"]
    if not isinstance(model, dict) or not all(isinstance(t, torch.Tensor) for t in model.values()):
        raise TorchtrackError(f"detector checkpoint {path}: 'model' is not a state dict of tensors")
    bad = [name for name, t in model.items() if t.is_floating_point() and not torch.isfinite(t).all()]
    if bad:
        raise TorchtrackError(f"detector checkpoint {path}: NaN or infinite weights in {bad[0]}"
                              + (f" and {len(bad) - 1} more" if len(bad) > 1 else ""))
    return data
