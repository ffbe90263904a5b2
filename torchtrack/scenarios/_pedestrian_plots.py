"""Figures of ``torchtrack scenario pedestrian``: paper Fig. 3 (positions over time) and Fig. 4 (OSPA)."""

from __future__ import annotations

from pathlib import Path

import torch

from torchtrack.scenarios._plots import plt, save
from torchtrack.scenarios.pedestrian import VARIANTS, PedestrianReport

COLORS = {"joint": "tab:blue", "inflated": "tab:orange", "naive": "tab:red", "inflated_kf": "tab:green"}


def plot_positions(path: Path, truth, run, variant: str) -> Path:
    """Fig. 3: true and estimated feature positions in x and y over time, run 0."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    T = truth.present.shape[0]
    steps = torch.arange(T)
    for a, (ax, name) in enumerate(zip(axes, ("x", "y"))):
        for f in range(truth.features.shape[1]):
            val = torch.where(truth.present[:, f], truth.features[:, f, a], torch.tensor(float("nan")))
            ax.plot(steps, val, color="k", lw=1.2, label="true" if f == 0 else None)
        m = run.mask[:, 0]
        t_idx = steps[:, None].expand_as(m)[m]
        ax.scatter(t_idx, run.position[:, 0, :, a][m], c=run.label[:, 0][m] % 10, cmap="tab10", s=2,
                   label=f"{variant} estimates (colour = label)")
        ax.set_ylabel(f"{name} [m]")
        ax.grid(alpha=0.3)
    axes[0].set_title("Feature positions: truth (f1 static, f2 pedestrian) and estimates, run 0")
    axes[0].legend(loc="upper left", markerscale=4)
    axes[1].set_xlabel("time step")
    return save(fig, path, dpi=120)


def plot_ospa(path: Path, per_step: dict, mean: dict) -> Path:
    """Fig. 4: OSPA (c = 20 m, p = 2) over time, averaged over runs."""
    fig, ax = plt.subplots(figsize=(9, 4))
    for v in sorted(per_step, key=lambda k: -mean[k]):          # the worst first, so the best is on top
        ax.plot(per_step[v].numpy(), lw=0.9, color=COLORS.get(v), label=f"{v} (mean {mean[v]:.2f})")
    ax.set_xlabel("time step")
    ax.set_ylabel("OSPA [m]")
    ax.set_title("Feature OSPA over time (mean over runs)")
    ax.grid(alpha=0.3)
    ax.legend()
    return save(fig, path, dpi=120)


def plot(report: PedestrianReport, out: Path) -> list[Path]:
    """Fig. 3 of every variant and Fig. 4 of the paper's variants, in the folder ``out``."""
    paths = [plot_positions(out / f"pedestrian_positions_{v}.png", report.truth, r, v)
             for v, r in report.variants.items()]
    return paths + [plot_ospa(out / "pedestrian_ospa.png", {v: report.ospa_per_step[v] for v in VARIANTS},
                              report.mean_ospa)]
