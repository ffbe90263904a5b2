"""Figures of the maneuver scenario, in the style of the paper's Fig. 1–9 (first run shown)."""

from __future__ import annotations

from pathlib import Path

from torchtrack.scenarios._plots import plt, save
from torchtrack.scenarios.maneuver import ManeuverReport


def plot(report: ManeuverReport, out: Path) -> list[Path]:
    """Write the three experiments' figures to the folder ``out``."""
    st, cv, mv, cfg = report.stationary, report.constant_velocity, report.maneuver, report.config

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    z, est, truth = st["seq"].measurements[:, 0], st["estimate"][:, 0], st["seq"].truth[:, 0]
    for i, (ax, name) in enumerate(zip(axes, ["latitude", "longitude"])):
        ax.plot(z[:, i] - truth[0, i], "o", ms=3, mfc="none", label="measured")
        ax.plot(est[:, i] - truth[0, i], "-", label="Kalman estimate")
        ax.axhline(0, color="k", lw=0.8, label="true")
        ax.set(xlabel="scan", ylabel=f"{name} − true (arcsec)", title=f"stationary target: {name}")
        ax.legend()
    paths = [save(fig, out / "stationary.png")]

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    seq, res = cv["seq"], cv["result"]
    for i, (ax, name) in enumerate(zip(axes, ["x", "y"])):
        ax.plot(seq.measurements[:, 0, i], "+", label="measured")
        ax.plot(seq.truth[:, 0, i], "k-", lw=1, label="true")
        ax.plot(res.mean[:, 0, i], "r.", ms=3, label="estimated")
        ax.set(xlabel="scan", ylabel=f"{name} (m)", title=f"constant-velocity target: {name}")
        ax.legend()
    paths.append(save(fig, out / "constant_velocity.png"))

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    seq = mv["seq"]
    ax = axes[0]
    ax.plot(seq.measurements[:, 0, 0], seq.measurements[:, 0, 1], "+", color="0.6", ms=4, label="measured")
    ax.plot(seq.truth[:, 0, 0], seq.truth[:, 0, 1], "k-", lw=1.2, label="true")
    ax.plot(mv["plain"].mean[:, 0, 0], mv["plain"].mean[:, 0, 1], "-", lw=1, label="Kalman filter")
    ax.plot(mv["detecting"].mean[:, 0, 0], mv["detecting"].mean[:, 0, 1], "-", lw=1, label="with maneuver detection")
    det = mv["detecting"].detected[:, 0]
    ax.plot(seq.measurements[det, 0, 0], seq.measurements[det, 0, 1], "rv", label="maneuver declared")
    ax.set(xlabel="x (m)", ylabel="y (m)", title="maneuvering target (run 1)")
    ax.axis("equal")
    ax.legend(fontsize=8)
    ax = axes[1]
    ax.semilogy(range(1, seq.truth.shape[0] + 1), mv["detecting"].d2[:, 0].clamp_min(1e-3), "-",
                label="d² (detecting filter)")
    ax.axhline(cfg["filter"]["threshold"], color="r", ls="--", label=f"threshold {cfg['filter']['threshold']:g}")
    for onset in cfg["maneuver"]["onsets"]:
        ax.axvline(onset, color="k", ls=":", lw=1)
    ax.set(xlabel="scan", ylabel="normalised distance d²", title="residual test (paper Fig. 9)")
    ax.legend(fontsize=8)
    paths.append(save(fig, out / "maneuver.png"))
    return paths

