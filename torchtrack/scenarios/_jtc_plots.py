"""Figures of the JTC scenario in the style of the paper's Fig. 1–3 (means over the runs)."""

from __future__ import annotations

from pathlib import Path

from torchtrack.scenarios._plots import plt, save
from torchtrack.scenarios.jtc import JTCReport


def plot(report: JTCReport, out: Path) -> list[Path]:
    """Write the three figures to the folder ``out``."""
    traj, results = report.trajectory, report.results
    main = results[report.speed_constraints]
    scans = range(1, traj.states.shape[0])

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    xy = traj.states[:, :2] / 1e3
    axes[0].plot(xy[:, 0], xy[:, 1], "k.-", ms=3)
    man = traj.maneuvering
    axes[0].plot(xy[1:][man, 0], xy[1:][man, 1], "r.", ms=5, label="maneuvering")
    axes[0].plot(xy[0, 0], xy[0, 1], "go", label="start")
    axes[0].set(xlabel="x [km]", ylabel="y [km]", title="(a) test trajectory")
    axes[0].axis("equal")
    axes[0].legend()
    axes[1].plot(scans, main["mode1_probability"], "b-")
    axes[1].set(xlabel="scan", ylabel="probability", ylim=(0, 1.05), title="(b) posterior probability of mode 1")
    paths = [save(fig, out / "jtc_fig1_trajectory_mode.png")]

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, setting, name in zip(axes, (False, True), ("(a) without", "(b) with")):
        p = results[setting]["class_probability_correct"]
        ax.plot(scans, p, "r-", label=f"class {report.true_class} (true)")
        ax.plot(scans, 1 - p, "b--", label=f"class {3 - report.true_class}")
        ax.set(xlabel="scan", ylabel="class probability", ylim=(0, 1.05), title=f"{name} speed constraints")
        ax.legend()
    paths.append(save(fig, out / "jtc_fig2_class_probabilities.png"))

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    axes[0].plot(scans, main["rmse_position"], "b-")
    axes[0].set(xlabel="scan", ylabel="RMSE [m]", title="(a) position RMSE")
    axes[1].plot(scans, main["rmse_speed"], "b-")
    axes[1].set(xlabel="scan", ylabel="RMSE [m/s]", title="(b) speed RMSE")
    paths.append(save(fig, out / "jtc_fig3_rmse.png"))
    return paths
