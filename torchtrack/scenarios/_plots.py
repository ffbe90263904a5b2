"""Matplotlib for the scenarios' figures: the non-interactive backend and one way of saving a figure."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)

from torchtrack.io.outputs import save_figure  # noqa: E402

__all__ = ["plt", "save"]


def save(fig, path: Path, dpi: int = 110) -> Path:
    """Lay ``fig`` out, write it to ``path`` at ``dpi`` (whole: :func:`torchtrack.io.outputs.save_figure`) and
    close it."""
    return save_figure(fig, path, dpi=dpi)
