"""Figures of Fan et al. 2021: paths on the grid (Fig. 5), reward and steps per round (Fig. 6-7), formation (Fig. 8).

Real obstacles are black, virtual obstacles (section 3.2) grey, the start red, the goal yellow, as
in the paper. Every function writes one PNG and returns its path.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Patch, Rectangle  # noqa: E402

_CMAP = ListedColormap(["white", "0.72", "black"])  # free, virtual, real


def draw_grid(ax, occupancy: np.ndarray, virtual: np.ndarray | None = None, start=None, goal=None) -> None:
    """The grid: cell (x, y) is the unit square centred on (x, y)."""
    occ = np.asarray(occupancy, bool)
    img = occ.astype(int) * 2
    if virtual is not None:
        img[np.asarray(virtual, bool) & ~occ] = 1
    nx, ny = occ.shape
    ax.imshow(img.T, origin="lower", cmap=_CMAP, vmin=0, vmax=2, extent=(-0.5, nx - 0.5, -0.5, ny - 0.5))
    ax.set_xticks(np.arange(-0.5, nx, 1), minor=True)
    ax.set_yticks(np.arange(-0.5, ny, 1), minor=True)
    ax.grid(which="minor", color="0.85", lw=0.4)
    ax.tick_params(which="minor", length=0)
    ax.set_xticks(range(0, nx, 5))
    ax.set_yticks(range(0, ny, 5))
    for cell, color in ((start, "red"), (goal, "gold")):
        if cell is not None:
            ax.add_patch(Rectangle((cell[0] - 0.5, cell[1] - 0.5), 1, 1, color=color, zorder=3))
    ax.set_xlim(-0.5, nx - 0.5)
    ax.set_ylim(-0.5, ny - 0.5)
    ax.set_aspect("equal")


def _legend(ax) -> None:
    ax.legend(handles=[Patch(color="black", label="obstacle"), Patch(color="0.72", label="virtual obstacle"),
                       Patch(color="red", label="start"), Patch(color="gold", label="goal")],
              loc="upper left", fontsize=6, framealpha=0.8)


def _draw_result(ax, res) -> None:
    draw_grid(ax, res.occupancy, res.virtual, res.start, res.goal)
    p = np.asarray(res.path, float)
    ax.plot(p[:, 0], p[:, 1], "-", color="red", lw=1.8, zorder=4)
    ax.plot(p[:, 0], p[:, 1], ".", color="darkred", ms=3, zorder=4)
    if res.converged:
        sub = f"round {res.convergence_round}, {res.steps} steps, length {res.path_length:.2f}"
    else:
        sub = f"did not converge in {res.rounds} rounds" + ("" if res.greedy_reached else " (last round shown)")
    ax.set_title(f"{res.variant} (seed {res.seed})\n{sub}", fontsize=8)


def plot_path(res, path: str | Path) -> Path:
    """Fig. 5 for one :class:`~.qlearning.QLearningResult`."""
    fig, ax = plt.subplots(figsize=(5, 5))
    _draw_result(ax, res)
    _legend(ax)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)


def plot_paths(results, path: str | Path) -> Path:
    """Fig. 5: one panel per result (e.g. Q-L1..Q-L5)."""
    n = len(results)
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.9), squeeze=False)
    for ax, res in zip(axes[0], results):
        _draw_result(ax, res)
    _legend(axes[0][0])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_curves(results, path: str | Path) -> Path:
    """Fig. 6 (cumulative reward per round) and Fig. 7 (steps per round), one column per result."""
    n = len(results)
    fig, axes = plt.subplots(2, n, figsize=(3.4 * n, 5), squeeze=False)
    for j, res in enumerate(results):
        r = np.arange(1, len(res.steps_per_round) + 1)
        axes[0][j].plot(r, res.reward_per_round, lw=0.7, color="tab:blue")
        axes[1][j].plot(r, res.steps_per_round, lw=0.7, color="tab:orange")
        axes[0][j].set_title(res.variant, fontsize=9)
        axes[1][j].set_xlabel("round")
        for ax in (axes[0][j], axes[1][j]):
            if res.converged:
                ax.axvline(res.convergence_round, color="0.5", ls="--", lw=0.8)
    axes[0][0].set_ylabel("cumulative reward")
    axes[1][0].set_ylabel("steps")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_formation(results, path: str | Path, titles=None) -> Path:
    """Fig. 8: the leader (red) and the followers (blue, green) with their start cells; one panel per run."""
    colors = ["red", "tab:blue", "tab:green", "tab:purple", "tab:orange"]
    n = len(results)
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 5.2), squeeze=False)
    for k, (ax, fr) in enumerate(zip(axes[0], results)):
        draw_grid(ax, fr.occupancy, fr.virtual, None, fr.goal)
        for i, traj in enumerate([fr.leader] + (fr.follower_paths or fr.followers)):
            p = np.asarray(traj, float)
            c = colors[i % len(colors)]
            ax.plot(p[:, 0], p[:, 1], "-", color=c, lw=1.8, zorder=4,
                    label="leader" if i == 0 else f"follower {i} (offset {tuple(fr.offsets[i - 1])})")
            ax.add_patch(Rectangle((p[0, 0] - 0.5, p[0, 1] - 0.5), 1, 1, color=c, zorder=5))
        # the triangle every 4 ticks
        for t in range(0, len(fr.leader), 4):
            tri = np.array([fr.leader[t]] + [f[t] for f in fr.followers] + [fr.leader[t]], float)
            ax.plot(tri[:, 0], tri[:, 1], "-", color="0.4", lw=0.6, zorder=3)
        e = fr.formation_error
        sub = f"mean formation error {e.mean():.2f} cells, max {e.max():.2f}; {'reached' if fr.reached else 'NOT reached'}"
        ax.set_title((titles[k] if titles else f"run {k}") + "\n" + sub, fontsize=9)
        ax.legend(loc="upper left", fontsize=7, framealpha=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


__all__ = ["draw_grid", "plot_path", "plot_paths", "plot_curves", "plot_formation"]
