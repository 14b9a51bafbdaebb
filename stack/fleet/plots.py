"""Plots of a run: trajectories with formation snapshots (Bai 2022 Fig. 9a) and distances (Fig. 9b)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Polygon  # noqa: E402

SNAPSHOT_S = 10.0


def _obstacle_patches(ax, obstacles) -> None:
    for o in obstacles:
        if o.type == "cylinder":
            ax.add_patch(Circle((o.x, o.y), o.radius, color="tab:red", alpha=0.6))
        else:
            cx, cy, hx, hy, yaw = o.as_box()
            c, s = np.cos(yaw), np.sin(yaw)
            corners = [(cx + c * dx - s * dy, cy + s * dx + c * dy) for dx, dy in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]
            ax.add_patch(Polygon(corners, color="tab:red", alpha=0.6))


def plot_trajectories(sc, log, path: Path) -> None:
    """Every robot's path (the leader dashed), its body and the formation's outline every SNAPSHOT_S."""
    ids, t, X, Y = log.ids, log.t, log.x, log.y
    fig, ax = plt.subplots(figsize=(10, 6))
    _obstacle_patches(ax, sc.obstacles)
    leader = sc.formation.leader if sc.formation else None
    colors = plt.cm.tab10(np.linspace(0, 1, 10))
    for j, rid in enumerate(ids):
        style = "--" if rid == leader else "-"
        ax.plot(X[:, j], Y[:, j], style, color=colors[j % 10], lw=1.4,
                label=f"robot {rid}" + (" (leader)" if rid == leader else ""))
    # formation snapshots every 10 s, and the last one
    snaps = list(np.arange(0, t[-1] + 1e-9, SNAPSHOT_S))
    for ts in snaps + [t[-1]]:
        k = int(np.argmin(np.abs(t - ts)))
        pts = np.column_stack([X[k], Y[k]])
        if sc.formation and len(ids) > 2:
            order = np.argsort(np.arctan2(pts[:, 1] - pts[:, 1].mean(), pts[:, 0] - pts[:, 0].mean()))
            ax.add_patch(Polygon(pts[order], fill=False, ec="0.5", lw=0.8, ls=":"))
        for j, rid in enumerate(ids):
            r = sc.robot(rid).radius
            ax.add_patch(Circle(pts[j], r, fill=False, ec=colors[j % 10], lw=0.8))
        ax.annotate(f"{t[k]:.0f} s", pts.mean(axis=0), fontsize=7, color="0.3", ha="center")
    if sc.formation:
        ax.plot(*sc.formation.goal, "k*", ms=14, label="goal")
    else:
        for r in sc.robots:
            ax.plot(*r.goal, "k*", ms=10)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{sc.name}: trajectories, formation every {SNAPSHOT_S:.0f} s")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_distances(sc, t, dmin, dmax, dobs, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(9, 4))
    if np.isfinite(dmin).any():
        ax.plot(t, dmin, label="min robot distance")
        ax.plot(t, dmax, label="max robot distance")
    if np.isfinite(dobs).any():
        ax.plot(t, dobs, label="min obstacle distance")
    r = max(rb.radius for rb in sc.robots)
    ax.axhline(2 * r, color="tab:red", ls="--", lw=0.8, label="2 R_d (robot collision)")
    ax.axhline(r, color="tab:purple", ls=":", lw=0.8, label="R_d (obstacle collision)")
    ax.axhline(min(rb.comm_range for rb in sc.robots), color="0.4", ls="-.", lw=0.8, label="comm range")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("distance [m]")
    ax.set_title(f"{sc.name}: distances")
    ax.legend(fontsize=8, loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_errors(sc, t, errors: dict, path: Path) -> None:
    """Followers' slot errors along x and y over time (Deng Fig. 2b-c, 3b-e), schedule switches marked."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for rid, (ex, ey) in sorted(errors.items()):
        axes[0].plot(t, ex, label=f"follower {rid}")
        axes[1].plot(t, ey, label=f"follower {rid}")
    for ax, name in zip(axes, ("x", "y")):
        for ch in sc.formation.schedule:
            ax.axvline(ch.at, color="0.5", ls=":", lw=0.8)
        ax.axhspan(-0.05, 0.05, color="tab:green", alpha=0.15, lw=0)
        ax.set_xlabel("time [s]")
        ax.set_title(f"{name} error (slot - position)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("error [m]")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{sc.name}: formation errors (band: the 0.05 m of error_convergence_time_s)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
