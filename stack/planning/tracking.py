"""Follower tracking of Fan et al. 2021, section 4.1 (eq. 12-13), and the formation experiment of section 5.2.

The leader plans with the improved Q-learning (:mod:`.qlearning`, Q-L5) and broadcasts each step; a
follower's "target state at this time" is the leader's cell plus its formation offset (Step 1). The
follower scores its eight neighbouring states with the cost of eq. (13) and steps to the cheapest
one (Step 2), again until it stands on its target or has used its moves for this leader step
(Step 3). It fills concave cells with virtual obstacles like the leader (section 3.2, shared).

Readings where the paper is silent:

* d_attr of eq. (12) is in cells (with the 26 px cells of the Q-table's GPF, c * d would outweigh
  R_static = 1 and the follower would prefer an obstacle one cell nearer its target).
* R_static is charged for a real obstacle, a virtual one (except the follower's own target cell),
  off-grid cells, a corner clip and a cell held by another robot. The follower never enters a real
  obstacle, the map border or a robot: when the cheapest state is one of those it stays.
* "continues to accelerate": a follower may take up to ``max_moves`` steps per leader step
  (default 2; the leader's diagonal step is sqrt(2) long).
* The leader's own virtual obstacles are shared with the followers (the paper: "to share
  information"); a follower fills with respect to its current target.
* After the leader arrives the followers get ``settle_ticks`` more ticks to reach their cells.

Only numpy and the standard library (and this package) are imported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .grid import ACTIONS, Cell, GridWorld, check_cells, closer_actions
from .qlearning import QLearningConfig, QLearningResult, plan

#: Section 5.2: leader at (2, 2), followers at (0, 2) and (2, 0): offsets from the leader.
TRIANGLE_OFFSETS: tuple[Cell, ...] = ((-2, 0), (0, -2))


@dataclass
class TrackingConfig:
    """Arguments of the follower tracking strategy (section 4.1; values of section 5.2)."""

    c: float = 0.09
    """Adjustment coefficient c of eq. (13)."""
    R_static: float = 1.0
    """Penalty R_static of eq. (13) for a checked state that is an obstacle."""
    max_moves: int = 2
    """Most steps a follower takes per leader step (Step 3 loops back to Step 2 until on target)."""
    filling: bool = True
    """Followers fill concave cells with virtual obstacles too (section 4.1, Step 2)."""
    settle_ticks: int = 20
    """Ticks after the leader's arrival for the followers to reach their cells."""


def attraction(cell: Cell, target: Cell) -> float:
    """eq. (12): d_attr = sqrt((x_s - x_goal)^2 + (y_s - y_goal)^2), in cells."""
    return math.hypot(cell[0] - target[0], cell[1] - target[1])


def tracking_cost(cell: Cell, target: Cell, obstacle: bool, c: float = 0.09, R_static: float = 1.0) -> float:
    """eq. (13): C(s_t, a_t) = c * d_attr + R_static(s_t, a_t), R_static only when the state is an obstacle."""
    return c * attraction(cell, target) + (R_static if obstacle else 0.0)


@dataclass
class FormationResult:
    """Trajectories (one cell per tick) of the leader and the followers, and how well they kept formation."""

    leader: list[Cell]
    """The leader's cell at each tick."""
    followers: list[list[Cell]]
    """Each follower's cell at each tick."""
    offsets: list[Cell]
    follower_paths: list[list[Cell]]
    """Each follower's every step (up to ``max_moves`` per tick)."""
    occupancy: np.ndarray = field(repr=False)
    virtual: np.ndarray = field(repr=False)
    goal: Cell = (0, 0)
    leader_plan: QLearningResult | None = field(default=None, repr=False)

    @property
    def formation_error(self) -> np.ndarray:
        """Per tick, the mean distance (cells) of the followers from leader + offset."""
        L = np.asarray(self.leader, float)
        errs = [np.hypot(*(np.asarray(f, float) - (L + o)).T) for f, o in zip(self.followers, self.offsets)]
        return np.mean(errs, axis=0)

    @property
    def reached(self) -> bool:
        """Leader on the goal and every follower on goal + offset at the end."""
        g = self.goal
        return tuple(self.leader[-1]) == tuple(g) and all(
            tuple(f[-1]) == (g[0] + o[0], g[1] + o[1]) for f, o in zip(self.followers, self.offsets))

    def summary(self) -> dict:
        e = self.formation_error
        L = lambda p: float(sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(p, p[1:])))  # noqa: E731
        return {
            "reached": self.reached, "ticks": len(self.leader) - 1,
            "formation_error_mean": round(float(e.mean()), 4), "formation_error_max": round(float(e.max()), 4),
            "formation_error_final": round(float(e[-1]), 4),
            "leader_path_length": round(L(self.leader), 4),
            "follower_path_lengths": [round(L(f), 4) for f in self.follower_paths or self.followers],
            "leader": [list(c) for c in self.leader], "followers": [[list(c) for c in f] for f in self.followers],
            "follower_paths": [[list(c) for c in f] for f in self.follower_paths],
            "offsets": [list(o) for o in self.offsets], "goal": list(self.goal),
            "virtual_obstacles": [list(map(int, c)) for c in np.argwhere(self.virtual)],
        }


def _follower_step(world: GridWorld, pos: Cell, target: Cell, others: set, cfg: TrackingConfig) -> Cell:
    """Step 2 once: fill if concave, then move to the neighbour of least cost (eq. 13), or stay."""
    nx, ny = world.nx, world.ny
    occ, virt = world.occupancy, world.virtual

    def hard(x, y):  # cells a robot can never enter
        return not (0 <= x < nx and 0 <= y < ny) or occ[x, y] or (x, y) in others

    def static(x, y):  # what the sensor reports as obstacles (robots move on: never filled for)
        return not (0 <= x < nx and 0 <= y < ny) or occ[x, y] or (virt[x, y] and (x, y) != tuple(target))

    def obstacle(x, y):
        return static(x, y) or (x, y) in others

    x, y = pos
    if cfg.filling and tuple(pos) != tuple(target):  # section 3.2 with respect to the follower's target
        feasible = [a for a in closer_actions(pos, target) if not _clipped(static, x, y, a, world.corner_cutting)]
        if closer_actions(pos, target) and not feasible:
            world.fill(world.index(pos))
    best, best_cost = None, math.inf
    for a, (dx, dy) in enumerate(ACTIONS):
        cell = (x + dx, y + dy)
        cost = tracking_cost(cell, target, _clipped(obstacle, x, y, a, world.corner_cutting), cfg.c, cfg.R_static)
        if cost < best_cost:
            best, best_cost = a, cost
    dx, dy = ACTIONS[best]
    if _clipped(hard, x, y, best, world.corner_cutting):
        return pos
    return (x + dx, y + dy)


def _clipped(blocked, x: int, y: int, a: int, corner_cutting: bool) -> bool:
    dx, dy = ACTIONS[a]
    if blocked(x + dx, y + dy):
        return True
    return bool(dx and dy and not corner_cutting and (blocked(x + dx, y) or blocked(x, y + dy)))


def run_formation(occupancy: np.ndarray, leader_path: list[Cell], follower_starts: list[Cell],
                  offsets: list[Cell], config: TrackingConfig | None = None,
                  virtual: np.ndarray | None = None) -> FormationResult:
    """Replay the leader's path one step per tick; each follower tracks leader + offset (section 4.1)."""
    cfg = config or TrackingConfig()
    occupancy = np.asarray(occupancy, bool)
    goal = tuple(leader_path[-1])
    check_cells(occupancy, leader=tuple(leader_path[0]), goal=goal,
                **{f"follower {i}": tuple(s) for i, s in enumerate(follower_starts)})
    world = GridWorld(occupancy, leader_path[0], goal, False, virtual)
    L = [tuple(leader_path[0])]
    F = [[tuple(s)] for s in follower_starts]
    P = [[tuple(s)] for s in follower_starts]
    n_ticks = len(leader_path) - 1 + cfg.settle_ticks
    for t in range(1, n_ticks + 1):
        lead = tuple(leader_path[min(t, len(leader_path) - 1)])
        L.append(lead)
        for i, off in enumerate(offsets):  # Step 1: the target at this time from the broadcast
            target = (lead[0] + off[0], lead[1] + off[1])
            pos = F[i][-1]
            for _ in range(cfg.max_moves):  # Step 3: back to Step 2 until on the target
                if pos == target:
                    break
                others = {L[-1]} | {F[j][-1] for j in range(len(F)) if j != i}
                new = _follower_step(world, pos, target, others, cfg)
                if new == pos:
                    break
                pos = new
                P[i].append(pos)
            F[i].append(pos)
        if t >= len(leader_path) - 1 and all(F[i][-1] == (goal[0] + o[0], goal[1] + o[1]) for i, o in enumerate(offsets)):
            break
    return FormationResult(L, F, [tuple(o) for o in offsets], P, occupancy.copy(), world.virtual.copy(), goal)


def formation_experiment(occupancy: np.ndarray | None = None, leader_start: Cell = (2, 2), goal: Cell = (19, 19),
                         offsets=TRIANGLE_OFFSETS, qconfig: QLearningConfig | None = None,
                         tconfig: TrackingConfig | None = None, shape: tuple[int, int] = (20, 20)) -> FormationResult:
    """Section 5.2: the leader plans with Q-L5 from ``leader_start`` to ``goal``, two followers keep the
    triangle. ``occupancy=None`` is the obstacle-free case (Fig. 8(a))."""
    occ = np.zeros(shape, bool) if occupancy is None else np.asarray(occupancy, bool)
    q = qconfig or QLearningConfig(variant="Q-L5")
    res = plan(occ, leader_start, goal, q)
    if not res.greedy_reached and not res.reached:
        raise RuntimeError(f"the leader's {q.variant} plan did not reach {goal} in {res.rounds} rounds")
    starts = [(leader_start[0] + o[0], leader_start[1] + o[1]) for o in offsets]
    out = run_formation(occ, res.path, starts, list(offsets), tconfig, virtual=res.virtual)
    out.leader_plan = res
    return out


__all__ = ["TrackingConfig", "FormationResult", "attraction", "tracking_cost", "run_formation",
           "formation_experiment", "TRIANGLE_OFFSETS"]
