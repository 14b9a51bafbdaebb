"""Improved Q-learning formation of Fan, Liu, Ning, Han, Wang, Yang, Liu (2021), online: ``--policy qlearn``.

The leader plans a grid path with the improved Q-learning of section 3 (variant Q-L5 of Table 1:
GPF Q-initialisation eq. (8)-(9), virtual obstacle filling section 3.2, SA greedy factor eq. (10)-(11),
reward r2 of eq. (14); :func:`stack.planning.qlearning.plan`) on an occupancy grid it builds from its
own lidar, and drives along the path. A follower tracks its formation slot with the GPF cost of
section 4.1, eq. (12)-(13):

  eq. (12)   d_attr = sqrt((x_s - x_goal)^2 + (y_s - y_goal)^2)
  eq. (13)   C(s_t, a_t) = c * d_attr + R_static(s_t, a_t),   c = 0.09, R_static = 1 (section 5.2)

The paper works on a 20 x 20 grid that is fully known to the planner after "trial-and-error
training", with robots that jump one cell per tick. **Choices where the paper is silent or where the
grid world meets continuous space** (all in :class:`QlearnPolicyConfig`):

Leader (and a peer without formation, which plans to its own goal the same way)
- *Map* (kept by followers too, as their obstacle memory). "An unknown environment where only the
  start and the target are known": the grid starts empty and is filled from the robot's own lidar
  only. It covers the bounding box of the start and the goal plus ``margin`` and grows (by
  ``margin`` more) whenever the robot comes within ``keep_on_grid`` of its edge or the goal leaves
  it (hits beyond the edge are dropped meanwhile; the grid's size is what a plan costs). Cells
  hold log-odds evidence: a beam ending before ``range - hit_margin`` adds
  ``hit`` at its end cell, the cells it passed (up to one cell short of its end) lose ``miss``;
  a cell is occupied while its evidence is > 0 (one hit marks it; about eight clean passes erase a
  wrongly marked one, e.g. a robot that was not in the neighbour list). Beams that end within
  ``radius + neighbour_gate`` of a known neighbour mark nothing (robots move), as in the decision
  layer's ``obstacle_distance``. ``hit_margin`` keeps noisy max-range beams from counting as hits.
- *Robot size.* The planner's cells are points; a cell is blocked when its centre is within
  ``(radius + clearance) / cell + 0.5`` cells of an occupied cell's centre (the half cell: the hit
  lies anywhere in its cell). The planner gets this inflated grid as its occupancy, so its motion
  rule (no corner cutting) keeps the path one clearance away from every hit.
- *Planning.* ``plan(blocked, robot cell, goal cell, Q-L5, fill_guard=True)``. If the robot's or the
  goal's cell is blocked (it came close to an obstacle), the nearest free cell stands in for it
  (``start_moved`` / ``goal_moved``). Before learning, a 4-connected flood fill checks that the goal
  can be reached at all (without corner cutting 8-connected reachability is 4-connected
  reachability); if not, no learning is run (``no_route``). A warm-started plan gets at most
  ``warm_rounds``; if it reaches no path, a cold plan follows (``cold_retry``: stale Q rows can hold
  the greedy walk in a loop, and once every round is cut at the step limit eq. (10) gives T = i, so
  eq. (11)'s epsilon is ~0 and nothing explores out of it). A run that does not converge but whose
  greedy or last round reached the goal still gives a path (``not_converged_best_path``), else the
  robot falls back (``fallback``) to the GPF chooser below aimed at the goal, and tries to plan again
  every ``retry_s``. ``max_rounds`` bounds a plan; a round is cut after ``4 (|dx| + |dy|) + 50``
  steps (paper: no limit; reading 1 of :mod:`stack.planning.qlearning`).
- *Replanning*, never periodic: (1) a cell that became occupied lies within the inflation plus
  ``replan_near`` cells of the rest of the path ("on or near the path"; warm start from the previous
  result: Q rows away from the change are kept); (2) the robot is more than ``off_path`` from the
  path; (3) the goal moved to another cell; (4) the grid grew (cold start: the Q-table's shape
  changed); (5) the guard below held the robot for ``stuck_s``. Triggers (2) and (5) wait
  ``replan_min_s`` after the last plan.
- *Path.* The paper's robot steps cell to cell (8 actions). Ours drives: the cell path's centres are
  string-pulled (``smooth``: a cell is skipped when the straight segment around it stays inside free
  cells, i.e. every sample's four nearest cell centres are free), the robot's position is
  prepended and the goal appended. Pure pursuit: aim at the point ``lookahead`` metres ahead along
  the path, w = k_heading * (bearing error), v = cruise * v_max * max(0, cos(bearing error)),
  times max(turn_min, cos(turn)) for the largest turn of the path within ``turn_horizon`` ahead,
  at most ``k_arrive`` * (distance to the goal); stop within ``arrive`` of the goal.
- *Guard* (ours, the paper's grid robot cannot graze an obstacle): a lidar end point (not on a
  neighbour) within ``radius + guard_margin`` in the front +-``guard_cone`` stops the translation.
- *Waiting for the followers*: the paper's leader steps once per tick while a follower may move more
  (:mod:`stack.planning.tracking`: two steps); ours cruises below v_max and slows like Bai's eq. (20),
  v * wait_distance / d_max, when the farthest neighbour is beyond ``wait_distance``.

Follower (section 4.1)
- *Step 1*: the target at this time is ``obs.target`` (the slot from the leader's broadcast pose).
- *Step 2 in continuous space*: one grid cell is ``step`` metres (default the planner's 0.5 m cell);
  the eight neighbouring states become ``n_headings`` points one step ahead on evenly spaced world
  headings (8 = the paper's actions; default 16), plus the point one step straight toward the
  target (so the continuous optimum is always a candidate; the step shrinks to the distance left).
  d_attr of eq. (12) is measured from each candidate point to the target point, in cells
  (metres / ``cell``, as :mod:`stack.planning.tracking` reads it). The target point is the slot
  moved ahead by its own velocity times ``lead_s`` (so a follower on a moving slot faces its motion).
  A candidate "is an obstacle" (R_static) when an obstacle point comes within
  ``radius + safety_margin`` of the candidate point or its midpoint and nearer than the robot is
  now (so a robot inside the band may still back out), or within ``radius + hard_margin`` at all;
  other robots (neighbours' centres) likewise with ``2 radius + robot_margin`` (a beam that ends on
  a neighbour counts through the neighbour's centre). Obstacle points: the follower keeps the same
  lidar grid as the leader (no planning on it), and each occupied cell remembers its latest exact
  hit point, so what the 180-degree lidar no longer sees (beside and behind) still counts until
  beams show the cell free again.
  The cheapest candidate wins; for ranking only, ``tie_bias`` per pi of turn from the current
  heading is added (the grid robot turns for free, a unicycle does not: without it the choice
  flips between going left and right round an obstacle and the robot spins in place).
- *Motion*: turn toward the chosen point (w = k_heading * error); speed
  v = min(v_max, k_v * distance to the slot + slot speed along the chosen heading) * max(0, cos(error)),
  zero when even the cheapest candidate is an obstacle (``follower_blocked``), while the robot's
  current heading fails the same obstacle test and is more than half a candidate spacing from the
  chosen one (``turn_first``: a unicycle moves along its heading while it turns toward the chosen
  point, so it turns in place first) or within ``arrive`` of a
  resting slot. The follower's virtual-obstacle filling (section 4.1 Step 2) is not done online.

Counters (``policy.counters``) and costs (``policy.stats``, ``policy.plan_times``) are kept for
reports and the benchmark (``bench/qlearn_policy_bench.py``). Imports: numpy, stdlib, stack.planning.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields

import numpy as np

from ..estimation.pose import wrap as _wrap
from ..planning.qlearning import QLearningConfig, QLearningResult, plan
from ..settings import check, rule
from .base import Observation, Policy

TWO_PI = 2.0 * math.pi
_COUNT = rule(">= 1", "<= 100000")


@dataclass
class QlearnPolicyConfig:
    """Parameters of ``--policy qlearn`` (scenario key ``robot.qlearn``); see the module docstring.
    Lengths, gains and counts are positive; ``evidence_min`` is a log-odds floor (any number up to 0)."""

    RULE = ("> 0",)

    # --- the leader's lidar grid
    cell: float = 0.5
    """Grid cell size [m] (the planner's state; also the follower's one step)."""
    margin: float = 5.0
    """The grid covers the bounding box of start and goal plus this [m]; it grows by this when needed."""
    clearance: float = 0.4
    """Inflation beyond the robot radius [m]: cells whose centre is within (radius + clearance) / cell + 0.5
    cells of an occupied cell's centre are blocked for the planner."""
    hit: float = 0.9
    """Log-odds added to a cell where a beam ends."""
    miss: float = 0.4
    """Log-odds removed from a cell a beam passes through (up to one cell short of its end)."""
    evidence_min: float = field(default=-1.0, metadata=rule("<= 0"))
    """Lower clamp of a cell's log-odds (a cell seen free long still takes two hits)."""
    evidence_max: float = 3.0
    """Upper clamp of a cell's log-odds (a wrongly marked cell takes about eight passes to clear)."""
    hit_margin: float = 0.1
    """A beam is a hit when its range is below range - this [m] (noisy max-range beams are not);
    raised to 4 lidar noise std by :func:`make_qlearn`."""
    keep_on_grid: float = 2.5
    """The grid grows when the robot comes within this [m] of its edge (lidar hits beyond the edge are
    dropped until then; the planner cannot route off the grid anyway)."""
    neighbour_gate: float = 0.3
    """A beam ending within radius + this [m] of a known neighbour marks nothing (robots move)."""
    # --- planning
    max_rounds: int = field(default=1000, metadata=_COUNT)
    """Most Q-learning rounds (episodes) per plan."""
    warm_rounds: int = field(default=200, metadata=_COUNT)
    """Most rounds of a warm-started plan; if it reaches no path, a cold plan (``max_rounds``) follows."""
    replan_near: int = field(default=1, metadata=_COUNT)
    """Replan when a newly occupied cell comes within the inflation plus this many cells of the path."""
    off_path: float = 1.0
    """Replan when the robot is more than this [m] from the path."""
    replan_min_s: float = 1.0
    """Off-path and stuck replans wait this long [s] after the last plan."""
    retry_s: float = 2.0
    """Without a path (fallback), try to plan again after this [s]."""
    stuck_s: float = 1.0
    """Replan when the guard has held the robot this long [s]."""
    smooth: bool = True
    """String-pull the cell path (drop cells whose shortcut stays inside free cells)."""
    # --- path following (leader)
    cruise: float = 0.6
    """Cruise speed, fraction of v_max."""
    lookahead: float = 1.0
    """Pure-pursuit lookahead along the path [m]."""
    k_heading: float = 2.0
    """Heading error -> angular velocity [1/s] (both roles; the driver clamps to w_max)."""
    turn_horizon: float = 1.5
    """Look this far [m] along the path for turns to slow down for."""
    turn_min: float = 0.3
    """Speed factor for a turn of 90 degrees or more (cos(turn) above)."""
    k_arrive: float = 1.0
    """Speed at most k_arrive * distance to the goal [1/s]."""
    arrive: float = 0.1
    """Stop within this of the goal [m] (a follower: of a resting slot)."""
    guard_margin: float = 0.15
    """Guard: stop translating when a lidar end point is within radius + this [m] ..."""
    guard_cone: float = math.radians(60.0)
    """... and within this bearing [rad] of straight ahead."""
    wait_distance: float = 6.0
    """The leader slows by wait_distance / d when its farthest neighbour is d > this [m] away (0: never)."""
    # --- follower tracking, eq. (12)-(13)
    c: float = 0.09
    """Adjustment coefficient c of eq. (13) (section 5.2), per cell of d_attr."""
    R_static: float = 1.0
    """Penalty R_static of eq. (13) for a candidate that is an obstacle (section 5.2)."""
    n_headings: int = field(default=16, metadata=_COUNT)
    """Candidate headings one step ahead (8 = the paper's eight actions), plus the straight one."""
    step: float | None = None
    """One step [m]; None = ``cell``."""
    safety_margin: float = 0.35
    """A lidar point within radius + this [m] of a candidate makes it an obstacle (if nearer than now)."""
    hard_margin: float = 0.1
    """... and within radius + this [m] always."""
    robot_margin: float = 0.5
    """A neighbour's centre within 2 radius + this [m] of a candidate makes it an obstacle (if nearer)."""
    k_v: float = 0.8
    """Follower speed per metre of distance to the slot [1/s] (plus the slot's own speed)."""
    lead_s: float = 0.5
    """The follower aims at the slot moved ahead by its velocity times this [s]."""
    tie_bias: float = 0.03
    """Cost added per pi of turn away from the current heading, when ranking (eq. (13) itself is reported
    without it): a unicycle's commitment. It breaks near-ties between far-apart headings (left or right
    round an obstacle on the line to the slot), which otherwise flip and cost a turn in place each time."""

    def __post_init__(self):
        check(self)

    @classmethod
    def from_dict(cls, d: dict | None) -> "QlearnPolicyConfig":
        names = {f.name for f in fields(cls)}
        d = dict(d or {})
        bad = sorted(set(d) - names)
        if bad:
            raise ValueError(f"unknown qlearn keys: {', '.join(bad)}")
        return cls(**d)


# ============================================================== the lidar grid

def dilate(mask: np.ndarray, r_cells: float) -> np.ndarray:
    """Cells whose centre is within ``r_cells`` (centre to centre) of a True cell."""
    out = mask.copy()
    R = int(math.floor(r_cells))
    nx, ny = mask.shape
    for dx in range(-R, R + 1):
        for dy in range(-R, R + 1):
            if (dx or dy) and dx * dx + dy * dy <= r_cells * r_cells:
                xs, xd = (slice(0, nx - dx), slice(dx, nx)) if dx >= 0 else (slice(-dx, nx), slice(0, nx + dx))
                ys, yd = (slice(0, ny - dy), slice(dy, ny)) if dy >= 0 else (slice(-dy, ny), slice(0, ny + dy))
                out[xd, yd] |= mask[xs, ys]
    return out


def reachable(blocked: np.ndarray, a: tuple[int, int], b: tuple[int, int]) -> bool:
    """4-connected flood fill over free cells from ``a``: can it reach ``b``? (Without corner cutting the
    planner's 8-connected moves reach exactly the 4-connected component.)"""
    free = ~blocked
    if not (free[a] and free[b]):
        return False
    reach = np.zeros_like(free)
    reach[a] = True
    while True:
        new = reach.copy()
        new[1:] |= reach[:-1]
        new[:-1] |= reach[1:]
        new[:, 1:] |= reach[:, :-1]
        new[:, :-1] |= reach[:, 1:]
        new &= free
        if new[b]:
            return True
        if np.array_equal(new, reach):
            return False
        reach = new


def nearest_free(blocked: np.ndarray, cell: tuple[int, int]) -> tuple[int, int] | None:
    free = np.argwhere(~blocked)
    if not len(free):
        return None
    k = int(np.argmin(((free - np.asarray(cell)) ** 2).sum(axis=1)))
    return int(free[k, 0]), int(free[k, 1])


class LidarGrid:
    """Log-odds occupancy on a world-aligned grid (cell (i, j) spans [i0 + i, i0 + i + 1) cells), ``[x, y]``."""

    def __init__(self, cfg: QlearnPolicyConfig, lo: tuple[float, float], hi: tuple[float, float]):
        self.cfg = cfg
        self.cell = cfg.cell
        c = self.cell
        self.i0, self.j0 = int(math.floor(lo[0] / c)), int(math.floor(lo[1] / c))
        i1, j1 = int(math.ceil(hi[0] / c)), int(math.ceil(hi[1] / c))
        self.L = np.zeros((max(1, i1 - self.i0), max(1, j1 - self.j0)), np.float32)
        self.H = np.zeros(self.L.shape + (2,), np.float64)  # the latest hit point [m, world] in each cell
        self.version = 0  # bumps when the grid grows (the planner's Q-table no longer fits)

    @property
    def shape(self) -> tuple[int, int]:
        return self.L.shape

    def bounds(self) -> tuple[float, float, float, float]:
        c = self.cell
        return self.i0 * c, self.j0 * c, (self.i0 + self.L.shape[0]) * c, (self.j0 + self.L.shape[1]) * c

    def ensure(self, lo: tuple[float, float], hi: tuple[float, float]) -> bool:
        """Grow (by ``margin`` beyond what is asked) so the box lo..hi is inside; True if it grew."""
        x0, y0, x1, y1 = self.bounds()
        if lo[0] >= x0 and lo[1] >= y0 and hi[0] <= x1 and hi[1] <= y1:
            return False
        m, c = self.cfg.margin, self.cell
        ni0 = min(self.i0, int(math.floor((lo[0] - m) / c))) if lo[0] < x0 else self.i0
        nj0 = min(self.j0, int(math.floor((lo[1] - m) / c))) if lo[1] < y0 else self.j0
        ei, ej = self.i0 + self.L.shape[0], self.j0 + self.L.shape[1]
        ni1 = max(ei, int(math.ceil((hi[0] + m) / c))) if hi[0] > x1 else ei
        nj1 = max(ej, int(math.ceil((hi[1] + m) / c))) if hi[1] > y1 else ej
        L = np.zeros((ni1 - ni0, nj1 - nj0), np.float32)
        H = np.zeros(L.shape + (2,), np.float64)
        ox, oy = self.i0 - ni0, self.j0 - nj0
        L[ox:ox + self.L.shape[0], oy:oy + self.L.shape[1]] = self.L
        H[ox:ox + self.L.shape[0], oy:oy + self.L.shape[1]] = self.H
        self.L, self.H, self.i0, self.j0 = L, H, ni0, nj0
        self.version += 1
        return True

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        return int(math.floor(x / self.cell)) - self.i0, int(math.floor(y / self.cell)) - self.j0

    def centres(self, cells) -> np.ndarray:
        a = np.asarray(cells, float).reshape(-1, 2)
        return (a + np.array([self.i0, self.j0]) + 0.5) * self.cell

    def _flat(self, x: np.ndarray, y: np.ndarray, with_mask: bool = False):
        i = np.floor(x / self.cell).astype(np.int64) - self.i0
        j = np.floor(y / self.cell).astype(np.int64) - self.j0
        nx, ny = self.L.shape
        ok = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        return (i[ok] * ny + j[ok], ok) if with_mask else i[ok] * ny + j[ok]

    def integrate(self, x: float, y: float, ang: np.ndarray, r: np.ndarray, hit_max: float,
                  on_robot: np.ndarray) -> np.ndarray:
        """One scan (world beam angles ``ang``, ranges ``r``) from (x, y); returns the flat indices of the
        cells that became occupied."""
        cfg, c = self.cfg, self.cell
        valid = np.isfinite(r) & (r >= 0)
        hit = valid & (r < hit_max)
        co, si = np.cos(ang), np.sin(ang)
        obst = hit & ~on_robot
        free_len = np.where(hit, r - c, np.minimum(np.where(valid, r, 0.0), hit_max))
        ts = np.arange(0.5 * c, max(hit_max, c), 0.5 * c)
        m = ts[None, :] < free_len[:, None]
        px = x + ts[None, :] * co[:, None]
        py = y + ts[None, :] * si[:, None]
        f_idx = np.unique(self._flat(px[m], py[m]))
        hx, hy = x + r[obst] * co[obst], y + r[obst] * si[obst]
        h_all, ok = self._flat(hx, hy, with_mask=True)
        self.H.reshape(-1, 2)[h_all] = np.column_stack([hx[ok], hy[ok]])
        h_idx = np.unique(h_all)
        if len(h_idx):
            f_idx = f_idx[~np.isin(f_idx, h_idx, assume_unique=True)]
        flat = self.L.reshape(-1)
        was = flat[h_idx] > 0
        flat[f_idx] = np.maximum(flat[f_idx] - cfg.miss, cfg.evidence_min)
        flat[h_idx] = np.minimum(flat[h_idx] + cfg.hit, cfg.evidence_max)
        return h_idx[~was & (flat[h_idx] > 0)]

    def occupied(self) -> np.ndarray:
        return self.L > 0

    def points_near(self, x: float, y: float, reach: float) -> np.ndarray:
        """The latest hit point of every occupied cell within ``reach`` [m] of (x, y): (k, 2). The grid is the
        robot's memory of what its 180-degree lidar no longer sees; the points keep the exact positions."""
        i0, j0 = self.cell_of(x - reach, y - reach)
        i1, j1 = self.cell_of(x + reach, y + reach)
        nx, ny = self.L.shape
        i0, j0, i1, j1 = max(i0, 0), max(j0, 0), min(i1 + 1, nx), min(j1 + 1, ny)
        if i0 >= i1 or j0 >= j1:
            return np.zeros((0, 2))
        pts = self.H[i0:i1, j0:j1][self.L[i0:i1, j0:j1] > 0]
        return pts[np.hypot(pts[:, 0] - x, pts[:, 1] - y) < reach]

    def inflation_cells(self, radius: float) -> float:
        return (radius + self.cfg.clearance) / self.cell + 0.5

    def blocked(self, radius: float) -> np.ndarray:
        return dilate(self.occupied(), self.inflation_cells(radius))


def _interior_free(blocked: np.ndarray, u: np.ndarray, v: np.ndarray) -> bool:
    """Every point (u, v) (continuous cell coordinates, cell centres at i + 0.5) has its four nearest
    cell centres free and on the grid."""
    i = np.floor(u - 0.5).astype(np.int64)
    j = np.floor(v - 0.5).astype(np.int64)
    nx, ny = blocked.shape
    if (i < 0).any() or (j < 0).any() or (i + 1 >= nx).any() or (j + 1 >= ny).any():
        return False
    return not (blocked[i, j].any() or blocked[i + 1, j].any() or blocked[i, j + 1].any()
                or blocked[i + 1, j + 1].any())


def string_pull(cells: list[tuple[int, int]], blocked: np.ndarray) -> list[tuple[int, int]]:
    """Greedy shortcuts: from each kept cell, jump to the farthest next cell (scanning forward until the
    first that cannot be seen) whose straight segment stays inside free cells."""
    if len(cells) <= 2:
        return list(cells)
    out = [cells[0]]
    i = 0
    n = len(cells)
    while i < n - 1:
        j = i + 1
        while j + 1 < n:
            a, b = np.asarray(cells[i], float) + 0.5, np.asarray(cells[j + 1], float) + 0.5
            k = max(2, int(math.ceil(np.hypot(*(b - a)) / 0.25)) + 1)
            t = np.linspace(0.0, 1.0, k)
            if not _interior_free(blocked, a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])):
                break
            j += 1
        out.append(cells[j])
        i = j
    return out


class Polyline:
    """A path for pure pursuit: points (M, 2), arc length, a monotonic progress."""

    def __init__(self, pts):
        p = np.asarray(pts, float).reshape(-1, 2)
        keep = np.ones(len(p), bool)
        keep[1:] = np.hypot(*np.diff(p, axis=0).T) > 1e-9
        self.p = p[keep]
        if len(self.p) == 1:
            self.p = np.vstack([self.p, self.p])
        d = np.diff(self.p, axis=0)
        self.seg_len = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        self.dir = d / self.seg_len[:, None]
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        self.length = float(self.cum[-1])
        self.s = 0.0

    def project(self, x: float, y: float, window: float = 3.0) -> tuple[float, float]:
        """Advance the progress to the nearest point of the segments that start within ``window`` of it;
        returns (s, distance to the path)."""
        n = len(self.dir)
        k0 = min(n - 1, max(0, int(np.searchsorted(self.cum, self.s, side="right")) - 1))
        k1 = min(n, max(k0 + 1, int(np.searchsorted(self.cum, self.s + window, side="right"))))
        a = self.p[k0:k1]
        dr = self.dir[k0:k1]
        L = self.seg_len[k0:k1]
        rel = np.array([x, y]) - a
        t = np.clip((rel * dr).sum(axis=1), 0.0, L)
        q = a + t[:, None] * dr
        dist = np.hypot(q[:, 0] - x, q[:, 1] - y)
        k = int(np.argmin(dist))
        s = float(self.cum[k0 + k] + t[k])
        self.s = max(self.s, s)
        return self.s, float(dist[k])

    def point_at(self, s: float) -> np.ndarray:
        s = min(max(s, 0.0), self.length)
        return np.array([np.interp(s, self.cum, self.p[:, 0]), np.interp(s, self.cum, self.p[:, 1])])

    def turn_within(self, s0: float, s1: float) -> float:
        """Largest heading change [rad] between the segment at s0 and those that start before s1."""
        k0 = min(len(self.dir) - 1, max(0, int(np.searchsorted(self.cum, s0, side="right")) - 1))
        k1 = min(len(self.dir), max(k0 + 1, int(np.searchsorted(self.cum, s1, side="right"))))
        h0 = math.atan2(self.dir[k0, 1], self.dir[k0, 0])
        turn = 0.0
        for k in range(k0 + 1, k1):
            turn = max(turn, abs(_wrap(math.atan2(self.dir[k, 1], self.dir[k, 0]) - h0)))
        return turn

    def samples(self, s0: float, step: float) -> np.ndarray:
        """Points every ``step`` from s0 to the end (and the end)."""
        ss = np.append(np.arange(s0, self.length, step), self.length)
        return np.column_stack([np.interp(ss, self.cum, self.p[:, 0]), np.interp(ss, self.cum, self.p[:, 1])])


# ============================================================== the follower's choice, eq. (12)-(13)

@dataclass
class TrackingChoice:
    theta: float
    """Chosen world heading [rad]."""
    cost: np.ndarray
    """eq. (13) per candidate (the straight one last)."""
    obstacle: np.ndarray
    """R_static charged per candidate."""
    thetas: np.ndarray
    index: int
    heading_obstacle: bool = False
    """Driving along the robot's current heading would come within the hard margin (turn before driving)."""

    @property
    def blocked(self) -> bool:
        return bool(self.obstacle[self.index])


def candidate_obstacles(p: tuple[float, float], thetas: np.ndarray, st: float, points: np.ndarray,
                        robots: np.ndarray, cfg: QlearnPolicyConfig, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """R_static's test per heading: the point one step ``st`` ahead or its midpoint comes within the
    safety band of a lidar point (or a robot) and nearer than the robot is now, or within the hard
    margin. Returns (obstacle, hard): the second for the hard margin alone."""
    px, py = p
    u = np.column_stack([np.cos(thetas), np.sin(thetas)])
    obstacle = np.zeros(len(thetas), bool)
    hard_hit = np.zeros(len(thetas), bool)
    for pts, band, hard in ((points, radius + cfg.safety_margin, radius + cfg.hard_margin),
                            (robots, 2 * radius + cfg.robot_margin, 2 * radius + cfg.hard_margin)):
        if pts is None or not len(pts):
            continue
        now = float(np.hypot(pts[:, 0] - px, pts[:, 1] - py).min())
        clr = np.full(len(thetas), np.inf)
        for f in (0.5, 1.0):
            q = np.array([px, py]) + f * st * u
            d = np.hypot(q[:, 0, None] - pts[None, :, 0], q[:, 1, None] - pts[None, :, 1]).min(axis=1)
            clr = np.minimum(clr, d)
        hard_hit |= clr < hard
        obstacle |= (clr < min(band, now - 1e-3)) | (clr < hard)
    return obstacle, hard_hit


def gpf_choice(p: tuple[float, float], aim: tuple[float, float], yaw: float, points: np.ndarray,
               robots: np.ndarray, cfg: QlearnPolicyConfig, radius: float) -> TrackingChoice:
    """Section 4.1 Step 2 in continuous space: eq. (13) over ``n_headings`` + 1 candidates one step ahead
    (the straight one last). ``points``: (k, 2) obstacle points [m, world]; ``robots``: (m, 2) other
    robots' centres. Also tests the current heading ``yaw`` (a unicycle moves along it while it turns)."""
    px, py = p
    dx, dy = aim[0] - px, aim[1] - py
    d_aim = math.hypot(dx, dy)
    step = cfg.step if cfg.step is not None else cfg.cell
    st = min(step, d_aim) if d_aim > 1e-6 else step
    n = cfg.n_headings
    thetas = np.append(TWO_PI * np.arange(n) / n, math.atan2(dy, dx))
    ends = np.column_stack([px + st * np.cos(thetas), py + st * np.sin(thetas)])
    d_attr = np.hypot(ends[:, 0] - aim[0], ends[:, 1] - aim[1]) / cfg.cell  # eq. (12), in cells
    obstacle, hard = candidate_obstacles(p, np.append(thetas, yaw), st, points, robots, cfg, radius)
    obstacle, heading_obstacle = obstacle[:-1], bool(hard[-1])
    cost = cfg.c * d_attr + cfg.R_static * obstacle  # eq. (13)
    ranked = cost + cfg.tie_bias * np.abs(np.angle(np.exp(1j * (thetas - yaw)))) / math.pi
    k = int(np.argmin(ranked))
    return TrackingChoice(float(thetas[k]), cost, obstacle, thetas, k, heading_obstacle)


# ============================================================== the policy

@dataclass(frozen=True)
class _PlanDone:
    """What a Q-L5 job hands back: the path in grid cells and world points (None: no path, fall back)."""

    result: QLearningResult | None
    cells: list[tuple[int, int]] | None
    points: list[tuple[float, float]] | None
    cold_retry: bool
    s: float
    """[s] what the plan cost: the asking step's share and the job's."""


@dataclass(frozen=True)
class _PlanAsk:
    """One Q-L5 plan as a pure function of a snapshot (the inflated grid, a copy; cells; the warm start, which
    :func:`plan` only reads; the grid's origin then), so it can run beside the control step."""

    blocked: np.ndarray
    start: tuple[int, int]
    goal: tuple[int, int]
    warm: QLearningResult | None
    seed: int
    cfg: QlearnPolicyConfig
    p: tuple[float, float]
    goal_xy: tuple[float, float] | None
    """The exact goal, appended to the path (None: the goal cell was blocked and moved)."""
    origin: tuple[int, int, float]
    """The grid's (i0, j0, cell) when asked: the path's world points."""
    asked_s: float

    def run(self) -> _PlanDone:
        t0 = time.perf_counter()
        cfg, s, gc, warm, cold = self.cfg, self.start, self.goal, self.warm, False
        res = None
        if s == gc:
            cells = [s]
        else:
            qc = QLearningConfig(variant="Q-L5", seed=self.seed, fill_guard=True,
                                 max_rounds=cfg.warm_rounds if warm is not None else cfg.max_rounds,
                                 max_steps=4 * (abs(s[0] - gc[0]) + abs(s[1] - gc[1])) + 50)
            res = plan(self.blocked, s, gc, qc, warm_start=warm)
            if warm is not None and not (res.converged or res.greedy_reached or res.reached):
                # stale Q rows can hold the greedy walk in a loop; with every round cut at max_steps the
                # step std is 0, eq. (10) gives T = i and eq. (11) epsilon ~ 0: no exploration gets it out
                cold = True
                qc.max_rounds = cfg.max_rounds
                res = plan(self.blocked, s, gc, qc)
            if not (res.converged or res.greedy_reached or res.reached):
                return _PlanDone(res, None, None, cold, self.asked_s + time.perf_counter() - t0)
            cells = [tuple(map(int, c)) for c in res.path]
        if cfg.smooth:
            cells = string_pull(cells, self.blocked)
        i0, j0, cell = self.origin
        pts = [self.p, *(((i + i0 + 0.5) * cell, (j + j0 + 0.5) * cell) for i, j in cells)]
        if self.goal_xy is not None:
            pts.append(self.goal_xy)
        return _PlanDone(res, cells, pts, cold, self.asked_s + time.perf_counter() - t0)


class QlearnPolicy(Policy):
    """``--policy qlearn``: the leader (or a peer) plans with Q-L5 on its lidar grid and pure-pursues the
    path; a follower tracks its slot with eq. (12)-(13)."""

    name = "qlearn"
    hybrid = False  # the paper's own avoidance: this policy drives in every situation

    def __init__(self, cfg: QlearnPolicyConfig | None = None, *, role: str | None, radius: float = 0.5,
                 v_max: float = 1.0, w_max: float = 1.0, lidar_fov: float = math.pi, lidar_range: float = 5.0,
                 lidar_noise: float = 0.0, seed: int = 0):
        self.cfg = cfg or QlearnPolicyConfig()
        self.role = role
        self.plans = role != "follower"  # a leader or a peer (None) plans to its own goal
        self.radius, self.v_max, self.w_max = radius, v_max, w_max
        self.fov, self.range = lidar_fov, lidar_range
        self.hit_margin = max(self.cfg.hit_margin, 4.0 * lidar_noise)
        self.seed = seed
        self.counters: dict[str, int] = {k: 0 for k in (
            "plans", "warm_plans", "replan_initial", "replan_blocked", "replan_off_path", "replan_goal_moved",
            "replan_grid_grew", "replan_stuck", "replan_retry", "converged", "not_converged_best_path",
            "cold_retry", "fallback", "no_route", "start_moved", "goal_moved", "guard_stops", "follower_blocked",
            "turn_first", "arrived")}
        self.plan_times: list[float] = []
        self.stats = {"acts": 0, "act_s_total": 0.0, "act_s_max": 0.0}
        self.last: dict = {}
        self.reset()

    def reset(self) -> None:
        self.t = 0.0
        self.grid: LidarGrid | None = None
        self.path: Polyline | None = None
        self.path_cells: list[tuple[int, int]] = []
        self.result: QLearningResult | None = None
        self._plan_goal_cell: tuple[int, int] | None = None
        self._plan_version = -1
        self._plan_t = -math.inf
        self._fallback = False
        self._guard_since: float | None = None
        self._check_path = False  # a plan adopted after it was asked for: check it against the grid of now
        self._gen = getattr(self, "_gen", 0) + 1  # a plan asked for before a reset is not adopted after it

    # ---------------------------------------------------------------- shared perception
    def _scan_world(self, obs: Observation, robots: np.ndarray):
        """World beam angles, ranges, hit mask and the 'ends on a neighbour' mask of the newest scan."""
        if obs.scans is None or obs.scans.size == 0:
            return None
        r = np.asarray(obs.scans[-1], float)
        n = len(r)
        rel = np.linspace(-self.fov / 2, self.fov / 2, n) if n > 1 else np.zeros(1)
        ang = obs.yaw + rel
        rng = obs.scan_range or self.range
        hit_max = rng - self.hit_margin
        hit = np.isfinite(r) & (r < hit_max)
        ex, ey = obs.x + r * np.cos(ang), obs.y + r * np.sin(ang)
        on_robot = np.zeros(n, bool)
        if len(robots):
            d = np.hypot(ex[:, None] - robots[None, :, 0], ey[:, None] - robots[None, :, 1]).min(axis=1)
            on_robot = hit & (d < self.radius + self.cfg.neighbour_gate)
        return ang, rel, r, hit, on_robot, ex, ey, hit_max

    @staticmethod
    def _robots(obs: Observation) -> np.ndarray:
        nb = np.asarray(obs.neighbours, float).reshape(-1, 2)
        if not len(nb):
            return np.zeros((0, 2))
        a = obs.yaw + nb[:, 1]
        return np.column_stack([obs.x + nb[:, 0] * np.cos(a), obs.y + nb[:, 0] * np.sin(a)])

    def _nearby_points(self, x: float, y: float, reach: float, sc=None) -> np.ndarray:
        """Obstacle points within ``reach``: the newest scan's end points (dense, exact; not those on a
        neighbour) and the grid's remembered points (what the lidar no longer sees)."""
        pts = self.grid.points_near(x, y, reach) if self.grid is not None else np.zeros((0, 2))
        if sc is not None:
            _, _, r, hit, on_robot, ex, ey, _ = sc
            keep = hit & ~on_robot & (r < reach)
            pts = np.concatenate([pts, np.column_stack([ex[keep], ey[keep]])])
        return pts

    @staticmethod
    def _target(obs: Observation) -> tuple[float, float]:
        if obs.target is not None:
            return float(obs.target[0]), float(obs.target[1])
        a = obs.yaw + obs.alpha_g
        return obs.x + obs.d_g * math.cos(a), obs.y + obs.d_g * math.sin(a)

    # ---------------------------------------------------------------- act
    def act(self, obs: Observation) -> tuple[float, float]:
        t0 = time.perf_counter()
        self.t += obs.dt
        robots = self._robots(obs)
        sc = self._scan_world(obs, robots)
        goal = self._target(obs)
        self._ensure_grid((obs.x, obs.y), goal)
        new_occ = np.zeros(0, np.int64)
        if sc is not None:
            ang, _, r, _, on_robot, _, _, hit_max = sc
            new_occ = self.grid.integrate(obs.x, obs.y, ang, r, hit_max, on_robot)
        if self.plans:
            v, w = self._act_leader(obs, goal, robots, sc, new_occ)
        else:
            v, w = self._act_follower(obs, robots, sc)
        w = max(-self.w_max, min(self.w_max, w))
        v = max(0.0, min(self.v_max, v))
        dt = time.perf_counter() - t0
        self.stats["acts"] += 1
        self.stats["act_s_total"] += dt
        self.stats["act_s_max"] = max(self.stats["act_s_max"], dt)
        return v, w

    # ---------------------------------------------------------------- follower, section 4.1
    def _act_follower(self, obs: Observation, robots: np.ndarray, sc) -> tuple[float, float]:
        cfg = self.cfg
        slot = self._target(obs)
        gvx, gvy = obs.goal_velocity
        d_slot = math.hypot(slot[0] - obs.x, slot[1] - obs.y)
        if d_slot < cfg.arrive and math.hypot(gvx, gvy) < 0.05:
            self.last = {"d_slot": d_slot, "v": 0.0, "w": 0.0}
            return 0.0, 0.0
        aim = (slot[0] + gvx * cfg.lead_s, slot[1] + gvy * cfg.lead_s)  # Step 1: the target at this time
        step = cfg.step if cfg.step is not None else cfg.cell
        pts = self._nearby_points(obs.x, obs.y, step + self.radius + cfg.safety_margin + 0.5, sc)
        reach_r = step + 2 * self.radius + cfg.robot_margin + 0.5
        near_r = robots[np.hypot(robots[:, 0] - obs.x, robots[:, 1] - obs.y) < reach_r] if len(robots) else robots
        ch = gpf_choice((obs.x, obs.y), aim, obs.yaw, pts, near_r, cfg, self.radius)  # Step 2
        err = _wrap(ch.theta - obs.yaw)
        speed = min(self.v_max, cfg.k_v * d_slot + max(0.0, gvx * math.cos(ch.theta) + gvy * math.sin(ch.theta)))
        if ch.blocked:
            self.counters["follower_blocked"] += 1
            speed = 0.0
        elif ch.heading_obstacle and abs(err) > math.pi / cfg.n_headings:  # a unicycle moves along its heading
            # while it turns: turn first (within half a candidate spacing the heading is the chosen one)
            self.counters["turn_first"] += 1
            speed = 0.0
        v = speed * max(0.0, math.cos(err))
        w = cfg.k_heading * err
        self.last = {"d_slot": d_slot, "theta": ch.theta, "cost": float(ch.cost[ch.index]), "blocked": ch.blocked,
                     "v": v, "w": w}
        return v, w

    # ---------------------------------------------------------------- leader / peer, section 3
    def _ensure_grid(self, p: tuple[float, float], goal: tuple[float, float]) -> None:
        m = self.cfg.margin
        reach = self.cfg.keep_on_grid + self.cfg.cell
        if self.grid is None:
            lo = (min(p[0], goal[0]) - m, min(p[1], goal[1]) - m)
            hi = (max(p[0], goal[0]) + m, max(p[1], goal[1]) + m)
            lo = (min(lo[0], p[0] - reach), min(lo[1], p[1] - reach))
            hi = (max(hi[0], p[0] + reach), max(hi[1], p[1] + reach))
            self.grid = LidarGrid(self.cfg, lo, hi)
            return
        c = self.cfg.cell
        lo = (min(p[0] - reach, goal[0] - c), min(p[1] - reach, goal[1] - c))
        hi = (max(p[0] + reach, goal[0] + c), max(p[1] + reach, goal[1] + c))
        self.grid.ensure(lo, hi)

    def _act_leader(self, obs: Observation, goal, robots: np.ndarray, sc, new_occ: np.ndarray) -> tuple[float, float]:
        cfg = self.cfg
        p = (obs.x, obs.y)
        d_goal = math.hypot(goal[0] - p[0], goal[1] - p[1])
        if d_goal < cfg.arrive:
            if not self.last.get("arrived"):
                self.counters["arrived"] += 1
            self.last = {"arrived": True, "v": 0.0, "w": 0.0}
            return 0.0, 0.0
        why = None if self.planner.busy("qlearn") else self._replan_reason(p, goal, new_occ)
        if why:
            self.counters["replan_" + why] += 1
            self._replan(p, goal)
        # guard: a lidar end point (not a neighbour) close ahead
        guard = False
        if sc is not None:
            _, rel, r, hit, on_robot, _, _, _ = sc
            close = hit & ~on_robot & (r < self.radius + cfg.guard_margin) & (np.abs(rel) < cfg.guard_cone)
            guard = bool(close.any())
        if self._fallback or self.path is None:
            v, w, info = self._drive_direct(obs, goal, sc)
        else:
            v, w, info = self._pursue(obs, goal, d_goal)
        if guard:
            self.counters["guard_stops"] += 1
            if self._guard_since is None:
                self._guard_since = self.t
            v = 0.0
        else:
            self._guard_since = None
        if cfg.wait_distance > 0 and len(obs.neighbours):
            d_far = float(np.max(np.asarray(obs.neighbours)[:, 0]))
            if d_far > cfg.wait_distance:
                v *= cfg.wait_distance / d_far
        self.last = {"v": v, "w": w, "guard": guard, "fallback": self._fallback, **info}
        return v, w

    def _replan_reason(self, p, goal, new_occ: np.ndarray) -> str | None:
        cfg, g = self.cfg, self.grid
        since = self.t - self._plan_t
        if self.result is None and self.path is None and not self._fallback:
            return "initial"
        if g.version != self._plan_version:
            return "grid_grew"
        if g.cell_of(*goal) != self._plan_goal_cell:
            return "goal_moved"
        if self._fallback or self.path is None:
            return "retry" if since >= cfg.retry_s else None
        if self._check_path:  # every cell that became occupied since the plan was asked for
            self._check_path = False
            new_occ = np.flatnonzero((g.occupied() & ~self._asked_occ).ravel())
        if len(new_occ):
            ny = g.shape[1]
            cells = np.column_stack(np.divmod(new_occ, ny))
            occ_xy = g.centres(cells)
            pts = self.path.samples(self.path.s, 0.5 * cfg.cell)
            reach = (g.inflation_cells(self.radius) + cfg.replan_near) * cfg.cell
            d = np.hypot(occ_xy[:, 0, None] - pts[None, :, 0], occ_xy[:, 1, None] - pts[None, :, 1])
            if (d <= reach).any():
                return "blocked"
        if since >= cfg.replan_min_s:
            _, dist = self.path.project(*p)
            if dist > cfg.off_path:
                return "off_path"
            if self._guard_since is not None and self.t - self._guard_since >= cfg.stuck_s:
                self._guard_since = None
                return "stuck"
        return None

    def _replan(self, p: tuple[float, float], goal: tuple[float, float]) -> None:
        """Ask for a plan from ``p`` to ``goal`` on the grid as it is now. The cheap part runs here (inflation,
        start and goal cells, reachability: no route falls back at once); Q-L5 itself runs on ``self.planner``
        (beside the control step, in an agent) on copies, and :meth:`_adopt` takes its path when it is done."""
        t0 = time.perf_counter()
        cfg, g = self.cfg, self.grid
        self._plan_t = self.t
        self._plan_version = g.version
        self._plan_goal_cell = g.cell_of(*goal)
        blocked = g.blocked(self.radius)
        s = g.cell_of(*p)
        gc = self._plan_goal_cell
        if blocked[s]:
            s = nearest_free(blocked, s)
            self.counters["start_moved"] += 1
        goal_moved = False
        if blocked[gc]:
            gc = nearest_free(blocked, gc)
            self.counters["goal_moved"] += 1
            goal_moved = True
        self.counters["plans"] += 1
        if s is None or gc is None or not reachable(blocked, s, gc):
            self.counters["no_route"] += 1
            self._set_fallback()
            self.plan_times.append(time.perf_counter() - t0)
            return
        warm = self.result if (self.result is not None and self.result.occupancy.shape == blocked.shape
                               and tuple(self.result.goal) == tuple(gc)) else None
        self.counters["warm_plans"] += warm is not None
        origin = (g.i0, g.j0, g.cell)
        self._asked_occ = g.occupied().copy()
        ask = _PlanAsk(blocked, s, gc, warm, self.seed + self.counters["plans"], cfg, p, None if goal_moved else goal,
                       origin, time.perf_counter() - t0)
        gen = self._gen
        self.planner.submit("qlearn", ask.run, lambda done: gen == self._gen and self._adopt(done))

    def _adopt(self, done: "_PlanDone") -> None:
        """A plan asked for earlier is done (the control thread, at the start of a step)."""
        self.plan_times.append(done.s)
        self.counters["cold_retry"] += done.cold_retry
        self.result = done.result
        if done.cells is None:
            self.counters["fallback"] += 1
            self._set_fallback()
            return
        if done.result is not None:
            self.counters["converged" if done.result.converged else "not_converged_best_path"] += 1
        self.path_cells = done.cells
        self.path = Polyline(done.points)
        self._fallback = False
        self._check_path = True  # what the grid learnt while the plan computed: checked at the next step

    def _set_fallback(self) -> None:
        self._fallback = True
        self.path = None
        self.path_cells = []

    def _pursue(self, obs: Observation, goal, d_goal: float):
        cfg = self.cfg
        s, dist = self.path.project(obs.x, obs.y)
        la = self.path.point_at(s + cfg.lookahead)
        err = _wrap(math.atan2(la[1] - obs.y, la[0] - obs.x) - obs.yaw)
        turn = min(self.path.turn_within(s, s + cfg.turn_horizon), math.pi / 2)
        v = cfg.cruise * self.v_max * max(0.0, math.cos(err)) * max(cfg.turn_min, math.cos(turn))
        v = min(v, cfg.k_arrive * d_goal)
        return v, cfg.k_heading * err, {"s": s, "path_dist": dist, "err": err}

    def _drive_direct(self, obs: Observation, goal, sc):
        """Fallback without a path: the GPF chooser of section 4.1 aimed at the goal, at cruise speed."""
        cfg = self.cfg
        step = cfg.step if cfg.step is not None else cfg.cell
        pts = self._nearby_points(obs.x, obs.y, step + self.radius + cfg.safety_margin + 0.5, sc)
        ch = gpf_choice((obs.x, obs.y), goal, obs.yaw, pts, np.zeros((0, 2)), cfg, self.radius)
        err = _wrap(ch.theta - obs.yaw)
        d_goal = math.hypot(goal[0] - obs.x, goal[1] - obs.y)
        turn_first = ch.heading_obstacle and abs(err) > math.pi / cfg.n_headings
        v = 0.0 if ch.blocked or turn_first else \
            min(cfg.cruise * self.v_max, cfg.k_arrive * d_goal) * max(0.0, math.cos(err))
        return v, cfg.k_heading * err, {"theta": ch.theta, "blocked": ch.blocked}


def make_qlearn(robot, *, seed: int = 0, **_) -> QlearnPolicy:
    """Factory: ``robot.qlearn`` (:class:`QlearnPolicyConfig`), the robot's role, radius, limits and lidar."""
    lidar = robot.lidar
    return QlearnPolicy(robot.config_for("qlearn"), role=robot.role, radius=robot.radius, v_max=robot.v_max,
                        w_max=robot.w_max, lidar_fov=lidar.fov, lidar_range=lidar.range,
                        lidar_noise=getattr(lidar, "noise_std", 0.0), seed=seed)


__all__ = ["QlearnPolicyConfig", "QlearnPolicy", "LidarGrid", "Polyline", "TrackingChoice", "gpf_choice",
           "dilate", "reachable", "nearest_free", "string_pull", "make_qlearn"]
