"""Figures for reports and the demo (host side; matplotlib with the Agg backend).

``plot_trajectory`` draws the paper's Fig. 3 (measured points against the true curve),
``plot_errors`` its Fig. 4 (per-axis differences and the Euclidean error over time).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_errors", "plot_measurement", "plot_trajectory"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> Path:
    """Write a figure atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    fig.savefig(tmp, dpi=120, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    tmp.replace(path)
    _pyplot().close(fig)
    return path


def plot_trajectory(
    path: str | Path,
    true_points: np.ndarray,
    measured_points: np.ndarray,
    camera_centres: np.ndarray | None = None,
    title: str = "Measured vs true trajectory",
    true_dense: np.ndarray | None = None,
) -> Path:
    """Fig. 3: measured points (red +) and the true motion (blue curve), in millimetres.

    Args:
        path: output PNG file.
        true_points, measured_points: (F, 3) in metres at the frame times.
        camera_centres: optional (F, 3) camera positions, drawn as grey dots.
        true_dense: optional (M, 3) densely sampled true curve for a smooth line.
    """
    plt = _pyplot()
    fig = plt.figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    line = np.asarray(true_dense if true_dense is not None else true_points) * 1e3
    ax.plot(*line.T, color="tab:blue", lw=1.5, label="true trajectory")
    m = np.asarray(measured_points) * 1e3
    ax.scatter(*m.T, marker="+", color="tab:red", s=25, label="measured")
    if camera_centres is not None:
        c = np.asarray(camera_centres) * 1e3
        ax.scatter(*c.T, marker=".", color="0.6", s=6, label="camera centres")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    ax.set_title(title)
    ax.legend(loc="upper left", fontsize=8)
    return _save(fig, path)


def plot_errors(
    path: str | Path,
    times: np.ndarray,
    true_points: np.ndarray,
    measured_points: np.ndarray,
    title: str = "Position difference, measured - true",
) -> Path:
    """Fig. 4: differences in x, y, z and the Euclidean error over time, in millimetres."""
    plt = _pyplot()
    diff = (np.asarray(measured_points) - np.asarray(true_points)) * 1e3
    eucl = np.linalg.norm(diff, axis=1)
    fig, axes = plt.subplots(4, 1, figsize=(7, 7.5), sharex=True)
    for a, name in enumerate("xyz"):
        axes[a].plot(times, diff[:, a], ".-", ms=3, lw=0.6)
        axes[a].axhline(0.0, color="0.5", lw=0.6)
        axes[a].set_ylabel(f"d{name} [mm]")
    axes[3].plot(times, eucl, ".-", ms=3, lw=0.6, color="tab:red")
    axes[3].axhline(eucl.mean(), color="k", lw=0.8, ls="--", label=f"mean {eucl.mean():.2f} mm")
    axes[3].set_ylabel("|d| [mm]")
    axes[3].set_xlabel("time [s]")
    axes[3].legend(fontsize=8)
    axes[0].set_title(title)
    return _save(fig, path)


def plot_measurement(
    path: str | Path,
    times: np.ndarray,
    assembly: np.ndarray,
    angles_deg: np.ndarray,
    ok: np.ndarray,
    title: str = "Measured workpiece",
) -> Path:
    """The measured assembly point (x, y, z [mm]) and workpiece rotation angle [deg] over
    time; frames without a pose are left out (no ground truth needed)."""
    plt = _pyplot()
    t, a, ang = times[ok], assembly[ok] * 1e3, angles_deg[ok]
    fig, axes = plt.subplots(4, 1, figsize=(7, 7.5), sharex=True)
    for i, name in enumerate("xyz"):
        axes[i].plot(t, a[:, i], ".-", ms=3, lw=0.6)
        axes[i].set_ylabel(f"{name} [mm]")
    axes[3].plot(t, ang, ".-", ms=3, lw=0.6, color="tab:purple")
    axes[3].set_ylabel("rotation [deg]")
    axes[3].set_xlabel("time [s]")
    axes[0].set_title(f"{title} ({int(ok.sum())}/{len(ok)} images with a pose)")
    return _save(fig, path)
