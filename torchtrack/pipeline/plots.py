"""Plots of a pipeline run: tracks over the first frame, MOTA / identity switches per tracker, and the rounds of
``train-detector --adapt``."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from torchtrack.io.outputs import save_figure  # noqa: E402
from torchtrack.io.video_writer import identity_color  # noqa: E402


def plot_tracks(first_frame: np.ndarray, tracks: dict[int, np.ndarray], path: str | Path,
                title: str = "", truth: dict[int, np.ndarray] | None = None) -> Path:
    """Each track's positions ``(T_i, 2)`` (first-frame / reference pixel coordinates) drawn as a line in
    its identity's colour over ``first_frame``; ``truth`` (same form) as thin white lines."""
    h, w = first_frame.shape[:2]
    fig, ax = plt.subplots(figsize=(7, 7 * h / w), dpi=110)
    ax.imshow(first_frame, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    for xy in (truth or {}).values():
        ax.plot(xy[:, 0], xy[:, 1], color="white", lw=0.6, alpha=0.6)
    for identity, xy in tracks.items():
        b, g, r = identity_color(identity)
        ax.plot(xy[:, 0], xy[:, 1], color=(r / 255, g / 255, b / 255), lw=1.2)
        ax.plot(xy[-1, 0], xy[-1, 1], "o", ms=2.5, color=(r / 255, g / 255, b / 255))
    ax.set_xlim(0, w - 1)
    ax.set_ylim(h - 1, 0)
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)
    return save_figure(fig, path)


def plot_scores(rows: dict[str, dict], path: str | Path) -> Path:
    """Bar charts of MOTA and identity switches (IDS) per tracker; ``rows`` tracker → CLEAR-MOT dict."""
    names = list(rows)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), dpi=110)
    x = np.arange(len(names))
    panels = (("MOTA", 100, "tab:blue", "%.1f", "MOTA (%)"), ("IDS", 1, "tab:red", "%g", "identity switches"))
    for ax, (key, scale, colour, fmt, label) in zip(axes, panels):
        ax.bar_label(ax.bar(x, [scale * rows[n][key] for n in names], color=colour), fmt=fmt, fontsize=8)
        ax.set_ylabel(label)
        ax.set_xticks(x, names, rotation=20, fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    return save_figure(fig, path)


def plot_rounds(rounds: list[dict], path: str | Path) -> Path:
    """Per round of ``train-detector --adapt`` (``report.json``'s rows): the pseudo-labels and how much of them
    changed since the previous round."""
    r = [row["round"] for row in rounds]
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.0), dpi=110)
    axes[0].plot(r, [row["pseudo_labels"] for row in rounds], "o-", color="tab:blue")
    axes[0].set_ylabel("pseudo-labels")
    axes[1].plot(r, [100 * row["change"] for row in rounds], "o-", color="tab:red")
    axes[1].set_ylabel("changed since the previous round (%)")
    for ax in axes:
        ax.set_xlabel("round")
        ax.set_xticks(r)
        ax.grid(alpha=0.3)
    return save_figure(fig, path)
