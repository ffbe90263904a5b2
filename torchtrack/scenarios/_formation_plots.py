"""Figures of the formation scenario: true tracks (paper Fig. 1) and estimates per gate (Fig. 2–4)."""

from __future__ import annotations

from pathlib import Path

from torchtrack.scenarios._plots import plt, save
from torchtrack.scenarios.formation import FormationReport

_COLOURS = ["tab:blue", "tab:red", "tab:green", "tab:orange", "tab:purple", "tab:brown"]


def plot(report: FormationReport, out_dir: Path) -> list[Path]:
    """Write ``formation_truth.png`` and ``formation_<gate>.png`` of the run where the ellipsoidal gate loses most
    associations (stated in the titles)."""
    data = report.data
    ell = report.results["ellipsoidal"]
    run = int((ell["detected"] & ~ell["correct"]).sum((1, 2)).argmax())
    estimates = {report.names[g]: r["estimate"] for g, r in report.results.items()}
    truth = data.truth[run].numpy()
    z, m, org = data.z[run].numpy(), data.z_mask[run].numpy(), data.z_origin[run].numpy()
    rep = data.z_class[run].numpy()
    classes = data.target_class.tolist()

    def frame(ax, title):
        for n in range(truth.shape[1]):
            ax.plot(truth[:, n, 0], truth[:, n, 1], "k--", lw=0.8)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(title)

    fig, ax = plt.subplots(figsize=(8, 4.5))
    frame(ax, f"True formation tracks, run {run} (classes " + ", ".join(str(c + 1) for c in classes) + ")")
    for c, colour in zip(range(int(rep.max()) + 1), ("tab:blue", "tab:red", "tab:green", "tab:orange")):
        sel = m & (org >= 0) & (rep == c)
        ax.scatter(z[sel][:, 0], z[sel][:, 1], s=5, c=colour, label=f"measurements reported class {c + 1}")
    ax.scatter(z[m & (org == -1)][:, 0], z[m & (org == -1)][:, 1], s=12, c="k", marker="x", label="clutter")
    ax.legend(loc="upper left", fontsize=8)
    paths = [save(fig, out_dir / "formation_truth.png", dpi=120)]

    for gate, est in estimates.items():
        e = est[run].numpy()
        fig, ax = plt.subplots(figsize=(8, 4.5))
        frame(ax, f"Estimated trajectories via the {gate.replace('_', ' ')} gate (run {run})")
        for n in range(e.shape[1]):
            ax.plot(e[:, n, 0], e[:, n, 1], "-", color=_COLOURS[n % len(_COLOURS)], lw=1.4,
                    label=f"track {n + 1} (class {classes[n] + 1})")
        ax.legend(loc="upper left", fontsize=8)
        paths.append(save(fig, out_dir / f"formation_{gate}.png", dpi=120))
    return paths
