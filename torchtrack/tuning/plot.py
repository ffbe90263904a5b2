"""Loss-curve plot of a fit (PNG, matplotlib Agg backend)."""

from __future__ import annotations

from pathlib import Path

from torchtrack.io.outputs import save_figure
from torchtrack.tuning.trainer import FitResult


def plot_loss_curve(result: FitResult, path: str | Path, title: str = "") -> Path:
    """Training loss per step and held-out loss per evaluation; the chosen step marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=(6, 4))
    steps = range(len(result.train_loss))     # the loss of step k is taken before its update
    ax.plot(steps, result.train_loss, label="training (mini-batch)", lw=1)
    if result.held_out:
        s, v = zip(*result.held_out)
        ax.plot(s, v, "o-", label="held-out", ms=3)
    if result.best_step is not None:
        ax.axvline(result.best_step, color="k", ls=":", lw=1, label=f"kept (after {result.best_step} updates)")
    ax.set_xlabel("parameter updates")
    ax.set_ylabel("loss")
    ax.set_title(title or "torchtrack tune")
    ax.legend()
    save_figure(fig, path, dpi=100)
    return path
