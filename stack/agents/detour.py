"""A planned detour for a stuck robot (ours, issue 19): a map of what its lidar has seen, and a grid path on it.

A local steering law (Deng's immune network, Bai's network, a tracking law) stands in front of a wall whose
gap lies off its line: every direction that leads to the gap first leads away from the goal. The stuck
detector (:mod:`.livelock`) notices; its blind escapes (a waypoint to the clearer side) rarely reach a gap
several metres away. Here the robot remembers every lidar return it has seen (:class:`ScanMemory`, cells of
``resolution``), and a planner finds the shortest 8-connected grid path from the robot to its target on that
memory, obstacles grown by the body's radius plus a margin, cells never seen counted free (optimistic: the
path runs along the known wall to its end, and as the robot drives, what it sees is added and the path
re-planned). The robot drives to a waypoint ``lookahead`` metres along the path.

The planner is a wavefront (Dijkstra by repeated relaxation, numpy) over a window around robot and target:
tens of milliseconds on a 40 m x 30 m window of 0.25 m cells, run only while a robot is stuck (once per
``replan_s``). Returns of known neighbours (robots move) are not remembered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ..settings import check, rule

SQRT2 = math.sqrt(2.0)
# the 8 neighbours (dx, dy) and their step costs (cells)
MOVES = [(1, 0, 1.0), (-1, 0, 1.0), (0, 1, 1.0), (0, -1, 1.0), (1, 1, SQRT2), (1, -1, SQRT2), (-1, 1, SQRT2), (-1, -1, SQRT2)]


@dataclass(frozen=True)
class DetourConfig:
    """The planned detour (``robot.stuck.detour``). Unknown keys are errors (a dataclass)."""

    enabled: bool = True
    """False: stuck robots escape blind only (the clearer side of the newest scan)."""
    resolution: float = field(default=0.25, metadata=rule("> 0", "<= 2"))
    """[m] the memory's and the planner's cell."""
    margin: float = field(default=0.1, metadata=rule(">= 0"))
    """[m] obstacles are grown by the robot's radius plus this."""
    pad: float = field(default=10.0, metadata=rule(">= 0"))
    """[m] the planning window: the box around robot and target, grown by this."""
    max_window: float = field(default=50.0, metadata=rule("> 0"))
    """[m] the longest side of the planning window (a target farther away is planned toward, clipped)."""
    near_cost: float = field(default=10.0, metadata=rule(">= 0"))
    """a cell within the grown body's reach of a return costs this much more than a free one (nearer than half
    the radius: blocked); so a robot pressed against a wall leaves it, and no path cuts a corner for a cell."""
    open_margin: float = field(default=1.0, metadata=rule(">= 0"))
    """[m] the straight way to the target is open (nothing to plan round; a detour under way hands back to the
    policy) when its next ``open_horizon`` metres keep the body this far beyond its radius off every return."""
    open_horizon: float = field(default=6.0, metadata=rule("> 0"))
    """[m] how far along the straight way :meth:`DetourPlanner.open_line` looks."""
    lookahead: float = field(default=2.0, metadata=rule("> 0"))
    """[m] the waypoint: this far along the path (path length)."""
    replan_s: float = field(default=1.0, metadata=rule("> 0"))
    """[s] re-plan on the grown memory this often while following a path."""
    max_time: float = field(default=30.0, metadata=rule("> 0"))
    """[s] the longest one planned detour drives before the detector judges progress again."""
    straight_time: float = field(default=10.0, metadata=rule("> 0"))
    """[s] the longest a plan down a straight way that is open (a stuck robot whose policy refuses it) drives."""
    max_cells: int = field(default=200_000, metadata=rule("> 0"))
    """the most cells the memory keeps (the oldest are forgotten first)."""
    tracker: Literal["pid", "policy"] = "pid"
    """What drives the robot to the path's waypoints: ``pid`` (the path tracker, blind to the other robots; the
    policy's own steering is what left it stuck) or ``policy`` (the robot's own policy, which sees them:
    ``bench/heldout.py``'s ``drl-alone``, so that every command outside Bai's situation 1 is the network's)."""

    def __post_init__(self):
        check(self)


class ScanMemory:
    """Cells where the lidar saw something (world frame), in the order first seen, bounded."""

    NO_RETURN = 0.02
    """a range within this fraction of ``range_max`` is nothing seen (a lidar's noise spreads its no-return value)."""

    def __init__(self, resolution: float = 0.25, max_cells: int = 200_000):
        self.res = resolution
        self.max_cells = max_cells
        self.cells: dict[tuple[int, int], None] = {}  # insertion-ordered set

    def add(self, x: float, y: float, yaw: float, scan: np.ndarray, fov: float, range_max: float,
            ignore: list[tuple[float, float]] = (), ignore_r: float = 0.8) -> None:
        """One scan taken at (x, y, yaw), beams evenly over -fov/2..fov/2; returns at ``range_max`` (nothing hit; with
        the lidar's noise, within ``NO_RETURN`` of it)
        and returns within ``ignore_r`` of an ``ignore`` point (a known robot) are not remembered."""
        scan = np.asarray(scan, float).ravel()
        if scan.size == 0:
            return
        ang = yaw + np.linspace(-fov / 2, fov / 2, scan.size)
        hit = np.isfinite(scan) & (scan < range_max - self.NO_RETURN * max(range_max, 1.0))
        px, py = x + scan[hit] * np.cos(ang[hit]), y + scan[hit] * np.sin(ang[hit])
        for ox, oy in ignore:
            keep = np.hypot(px - ox, py - oy) > ignore_r
            px, py = px[keep], py[keep]
        ix, iy = np.floor(px / self.res).astype(int), np.floor(py / self.res).astype(int)
        self.cells.update(dict.fromkeys(zip(ix.tolist(), iy.tolist())))
        while len(self.cells) > self.max_cells:
            del self.cells[next(iter(self.cells))]

    def window(self, x0: int, y0: int, nx: int, ny: int) -> np.ndarray:
        """(nx, ny) bool: the remembered cells in the window whose corner cell is (x0, y0)."""
        occ = np.zeros((nx, ny), bool)
        if self.cells:
            c = np.array(list(self.cells), int) - (x0, y0)
            c = c[(c[:, 0] >= 0) & (c[:, 0] < nx) & (c[:, 1] >= 0) & (c[:, 1] < ny)]
            occ[c[:, 0], c[:, 1]] = True
        return occ


def _shift(a: np.ndarray, dx: int, dy: int, fill) -> np.ndarray:
    """``a`` moved by (dx, dy) cells: out[i, j] = a[i - dx, j - dy]; ``fill`` where that is off the grid."""
    out = np.full_like(a, fill)
    nx, ny = a.shape
    out[max(dx, 0):nx + min(dx, 0), max(dy, 0):ny + min(dy, 0)] = a[max(-dx, 0):nx - max(dx, 0), max(-dy, 0):ny - max(dy, 0)]
    return out


def grow(occ: np.ndarray, r_cells: float) -> np.ndarray:
    """Occupied cells grown by a disk of ``r_cells`` (the configuration space of a round robot)."""
    out = occ.copy()
    k = int(math.ceil(r_cells))
    for dx in range(-k, k + 1):
        for dy in range(-k, k + 1):
            if (dx or dy) and dx * dx + dy * dy <= r_cells * r_cells:
                out |= _shift(occ, dx, dy, False)
    return out


def wavefront(cost: np.ndarray, goal: tuple[int, int], start: tuple[int, int]) -> np.ndarray:
    """Path cost from every cell to ``goal`` (inf: unreachable), a step into a cell costing its length (1 or
    sqrt 2 cells) times the cell's ``cost`` (inf: blocked), by relaxation in place (each of the 8 moves in turn
    over the whole grid, so one round carries a cost several cells), until a round changes nothing, or once
    ``start`` has a cost and as many rounds again (and 20) have passed."""
    nx, ny = cost.shape
    d = np.full((nx + 2, ny + 2), np.inf)  # a border of inf: no shifted copies needed
    d[goal[0] + 1, goal[1] + 1] = 0.0
    inner, ok = d[1:-1, 1:-1], np.isfinite(cost)
    step = {1.0: np.where(ok, cost, 0.0), SQRT2: np.where(ok, SQRT2 * cost, 0.0)}
    tmp, before = np.empty_like(cost), np.empty_like(cost)
    first = None
    for it in range(nx * ny):
        before[...] = inner
        for dx, dy, c in MOVES:
            np.add(d[1 + dx:nx + 1 + dx, 1 + dy:ny + 1 + dy], step[c], out=tmp)
            np.minimum(inner, tmp, out=inner, where=ok)
        if np.array_equal(before, inner):
            break
        if first is None and math.isfinite(inner[start]):
            first = it
        if first is not None and it > 2 * first + 20:
            break
    return inner.copy()


def descend(d: np.ndarray, start: tuple[int, int], max_cells: int) -> list[tuple[int, int]]:
    """The path from ``start`` down the cost field ``d`` to its zero: each step to the neighbour with the least
    cost plus step length, strictly lower than here (so it ends; at most ``max_cells`` cells)."""
    path = [start]
    i, j = start
    nx, ny = d.shape
    while d[i, j] > 0 and len(path) < max_cells:
        best = min(((d[i + dx, j + dy] + c, i + dx, j + dy) for dx, dy, c in MOVES
                    if 0 <= i + dx < nx and 0 <= j + dy < ny and d[i + dx, j + dy] < d[i, j]), default=None)
        if best is None:
            break
        i, j = best[1], best[2]
        path.append((i, j))
    return path


@dataclass(frozen=True)
class DetourPlan:
    """What one plan found: the window's grown cells, corner cell and returns' centres, and the path (world points,
    robot first; None: no way round)."""

    grid: tuple
    path: list[tuple[float, float]] | None


@dataclass(frozen=True)
class DetourAsk:
    """One detour plan on a snapshot of the memory (the window's remembered cells, a copy): a pure function."""

    occ: np.ndarray
    corner: tuple[int, int]
    res: float
    radius: float
    cfg: DetourConfig
    me: tuple[float, float]
    target: tuple[float, float]

    def run(self) -> DetourPlan:
        (x0, y0), r, occ = self.corner, self.res, self.occ
        nx, ny = occ.shape
        def cell(p: tuple[float, float]) -> tuple[int, int]:  # the window's cell of a point (clipped into it)
            return min(max(math.floor(p[0] / r) - x0, 0), nx - 1), min(max(math.floor(p[1] / r) - y0, 0), ny - 1)

        s, g = cell(self.me), cell(self.target)
        blocked = grow(occ, (self.radius + self.cfg.margin) / r)  # where the grown body would touch a return
        cost = np.where(blocked, 1.0 + self.cfg.near_cost, 1.0)  # dear there, not closed: a pressed robot may leave
        cost[grow(occ, self.radius / 2 / r)] = np.inf  # closed within half a radius of a return
        grid = (blocked, x0, y0, (np.argwhere(occ) + (x0 + 0.5, y0 + 0.5)) * r)
        d = wavefront(cost, g, s)
        if not math.isfinite(d[s]):
            return DetourPlan(grid, None)
        path = [((i + x0 + 0.5) * r, (j + y0 + 0.5) * r) for i, j in descend(d, s, nx * ny)]
        path[0] = self.me
        return DetourPlan(grid, path)


class DetourPlanner:
    """:meth:`plan` a grid path from a pose to a target on a :class:`ScanMemory`; :meth:`waypoint` along it."""

    def __init__(self, cfg: DetourConfig, memory: ScanMemory, radius: float):
        self.cfg = cfg
        self.memory = memory
        self.radius = radius
        self.path: list[tuple[float, float]] | None = None  # world points, robot first
        self.planned_at = -math.inf
        self.grid: tuple | None = None  # the last plan's window: grown cells, corner cell, centres of the returns

    def _window(self, a: tuple[float, float], b: tuple[float, float]) -> tuple[int, int, int, int]:
        c, r = self.cfg, self.memory.res
        lo = [min(a[k], b[k]) - c.pad for k in (0, 1)]
        hi = [max(a[k], b[k]) + c.pad for k in (0, 1)]
        for k in (0, 1):  # keep the robot in a window no longer than max_window
            if hi[k] - lo[k] > c.max_window:
                lo[k], hi[k] = max(lo[k], a[k] - c.max_window / 2), min(hi[k], a[k] + c.max_window / 2)
        x0, y0 = math.floor(lo[0] / r), math.floor(lo[1] / r)
        return x0, y0, math.ceil(hi[0] / r) - x0 + 1, math.ceil(hi[1] / r) - y0 + 1

    def plan(self, t: float, me: tuple[float, float], target: tuple[float, float]) -> bool:
        """Plan from ``me`` to ``target`` (clipped into the window) now; False (and no path) when none exists."""
        return self.adopt(self.ask(t, me, target).run())

    def ask(self, t: float, me: tuple[float, float], target: tuple[float, float]) -> "DetourAsk":
        """The plan as a job on a snapshot of the memory (:meth:`DetourAsk.run` may run beside the control step;
        :meth:`adopt` takes what it found)."""
        self.planned_at = t
        x0, y0, nx, ny = self._window(me, target)
        return DetourAsk(self.memory.window(x0, y0, nx, ny), (x0, y0), self.memory.res, self.radius, self.cfg, me, target)

    def adopt(self, found: "DetourPlan") -> bool:
        """A plan's result: its window and path (None: there is no way round). Whether there is a path."""
        self.grid, self.path = found.grid, found.path
        return found.path is not None

    def waypoint(self, me: tuple[float, float]) -> tuple[float, float] | None:
        """The farthest path point at most ``lookahead`` metres along the path (from its point nearest ``me``) that
        ``me`` reaches in a straight line clear of the grown cells (pure pursuit that cuts no corner); at least
        the next point."""
        if not self.path:
            return None
        p = np.asarray(self.path)
        k = int(np.argmin(np.hypot(p[:, 0] - me[0], p[:, 1] - me[1])))
        along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p[k:], axis=0).T))])
        best = p[min(k + 1, len(p) - 1)]
        for q, s in zip(p[k + 1:], along[1:]):
            if s > self.cfg.lookahead:
                break
            if self.clear_line(me, (float(q[0]), float(q[1]))):
                best = q
        return float(best[0]), float(best[1])

    def _samples(self, a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
        """Points every half cell (at least the two ends) along the segment a -> b: (M, 2)."""
        n = max(2, int(math.hypot(b[0] - a[0], b[1] - a[1]) / (self.memory.res / 2)))
        return np.column_stack([np.linspace(a[0], b[0], n), np.linspace(a[1], b[1], n)])

    def clearance(self, pts: np.ndarray) -> np.ndarray:
        """(M,) distance from each point (M, 2) to the nearest remembered return the last :meth:`plan` knew
        (a cell's centre, less half a cell); inf with none within reach of the grown body."""
        out = np.full(len(pts), np.inf)
        if self.grid is None or not len(pts):
            return out
        occ, reach = self.grid[3], self.radius + self.cfg.margin + self.memory.res
        near = occ[(occ[:, 0] > pts[:, 0].min() - reach) & (occ[:, 0] < pts[:, 0].max() + reach)
                   & (occ[:, 1] > pts[:, 1].min() - reach) & (occ[:, 1] < pts[:, 1].max() + reach)]
        if len(near):
            out = np.hypot(pts[:, None, 0] - near[None, :, 0], pts[:, None, 1] - near[None, :, 1]).min(axis=1)
            out -= self.memory.res / 2
        return out

    def open_line(self, me: tuple[float, float], target: tuple[float, float]) -> bool:
        """Whether the straight way toward ``target`` is open, as far as ``open_horizon`` (past that the lidar has
        seen nothing): it keeps the body ``radius`` + ``open_margin`` off every return the last :meth:`plan` knew;
        its first half metre only need not bring a robot already nearer than that nearer still."""
        c = self.cfg
        dist = math.hypot(target[0] - me[0], target[1] - me[1])
        f = min(1.0, c.open_horizon / dist) if dist > 0 else 0.0
        pts = self._samples(me, (me[0] + f * (target[0] - me[0]), me[1] + f * (target[1] - me[1])))
        cl = self.clearance(pts)
        need = np.full(len(pts), self.radius + c.open_margin)
        near = np.hypot(pts[:, 0] - me[0], pts[:, 1] - me[1]) < 0.5
        need[near] = np.minimum(need[near], cl[0] - 0.02)
        return bool(np.all(cl >= need))

    def clear_line(self, me: tuple[float, float], target: tuple[float, float]) -> bool:
        """Whether the straight line from ``me`` to ``target`` keeps the body ``radius`` + ``margin`` off every return
        the last :meth:`plan` knew, or (a robot already nearer than that) never brings it nearer than it is."""
        c = self.clearance(self._samples(me, target))
        need = min(self.radius + self.cfg.margin, float(c[0]) - 0.02)
        return bool(np.all(c[1:] >= need))
