"""The grid world of Fan et al. 2021, section 5: ASCII maps, 8 actions, a 3 x 3 sensor, virtual obstacles.

Conventions (the whole package uses them):

* an occupancy array is a boolean ``numpy`` array indexed ``occupancy[x, y]`` (shape ``(nx, ny)``),
  ``True`` = obstacle; cells are ``(x, y)`` integer pairs, x to the right, y up, both from 0;
* a state is the flat index ``s = x * ny + y`` (C order of ``occupancy``);
* the 8 actions are those of Algorithm 2 in its order: up, down, left, right, upleft, upright,
  downleft, downright (Fig. 2: one cell per step, diagonal steps are sqrt(2) long).

Map files (the contract): one text line per grid row, the first line is the top row (largest y),
x grows to the right from 0; ``#`` obstacle, ``.`` free, ``S`` the start, ``G`` the goal; every row
the same length. A malformed map raises :class:`MapError`, whose one-line message is
``FILE:LINE:COL: what`` (1-based line and column). Trailing empty lines and ``\\r`` line ends are
accepted; anything else (spaces, tabs, empty lines between rows) is an error.

Readings where the paper is silent (written down here once):

* Motion: a step into an obstacle (real or virtual) or off the grid is a collision. A diagonal step
  that would clip the corner of an obstacle (one of the two orthogonal cells it passes is blocked)
  is a collision too, unless ``corner_cutting=True``; a physical robot cannot squeeze between two
  diagonal blocks. The map border is a wall: the 3 x 3 sensor reads off-grid cells as obstacles.
* Section 3.2's feasibility test is the paper's, on cells: an adjacent position nearer the goal is
  "feasible" when it is on the grid and neither a real nor a virtual obstacle (a corner clip does not
  make it infeasible; the motion rule above is ours, the filling test stays the paper's).
* Filling can seal the start: every cell from which each strictly-nearer move is blocked may be
  filled, so when the way to the goal first leads away from it (the start behind a wall facing the
  goal) the whole shadow of the wall, start included, fills up. ``connected`` is there for a guard.

Only numpy and the standard library are imported here (the fleet will plan on lidar grids).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: (dx, dy) of the 8 actions, in the order of Algorithm 2.
ACTIONS: tuple[tuple[int, int], ...] = ((0, 1), (0, -1), (-1, 0), (1, 0), (-1, 1), (1, 1), (-1, -1), (1, -1))
ACTION_NAMES: tuple[str, ...] = ("up", "down", "left", "right", "upleft", "upright", "downleft", "downright")
#: length of each action's step (Fig. 2): 1 straight, sqrt(2) diagonal.
STEP_LENGTH: tuple[float, ...] = tuple(math.hypot(dx, dy) for dx, dy in ACTIONS)

#: maps/ at the repository root (shipped maps; :func:`find_map` looks here after the path itself).
MAPS_DIR = Path(__file__).resolve().parents[2] / "maps"

Cell = tuple[int, int]


class MapError(ValueError):
    """A malformed map; ``str(err)`` is one line: ``FILE:LINE:COL: what``."""

    def __init__(self, source: str, line: int, col: int, what: str):
        self.source, self.line, self.col, self.what = source, line, col, what
        super().__init__(f"{source}:{line}:{col}: {what}")


@dataclass(frozen=True)
class GridMap:
    """A parsed map: occupancy (``[x, y]``, True = obstacle), start and goal cells, where it came from."""

    occupancy: np.ndarray
    start: Cell
    goal: Cell
    source: str = "<grid>"

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupancy.shape  # (nx, ny)


def parse_map(text: str, source: str = "<string>") -> GridMap:
    """Parse the ASCII map format (see the module docstring); raise :class:`MapError` when malformed."""
    lines = text.split("\n")
    lines = [ln[:-1] if ln.endswith("\r") else ln for ln in lines]
    while lines and lines[-1] == "":
        lines.pop()
    if not lines:
        raise MapError(source, 1, 1, "empty map (no rows)")
    width = len(lines[0])
    if width == 0:
        raise MapError(source, 1, 1, "empty row")
    starts: list[tuple[int, int]] = []
    goals: list[tuple[int, int]] = []
    rows: list[list[bool]] = []
    for li, ln in enumerate(lines, start=1):
        if len(ln) != width:
            col = min(len(ln), width) + 1
            raise MapError(source, li, col, f"row has {len(ln)} cells, expected {width} (the length of line 1)")
        row = []
        for ci, ch in enumerate(ln, start=1):
            if ch == "#":
                row.append(True)
                continue
            if ch == "S":
                if starts:
                    raise MapError(source, li, ci, f"second start 'S' (the first is at {starts[0][0]}:{starts[0][1]})")
                starts.append((li, ci))
            elif ch == "G":
                if goals:
                    raise MapError(source, li, ci, f"second goal 'G' (the first is at {goals[0][0]}:{goals[0][1]})")
                goals.append((li, ci))
            elif ch != ".":
                raise MapError(source, li, ci, f"unknown character {ch!r} (expected '#', '.', 'S' or 'G')")
            row.append(False)
        rows.append(row)
    if not starts:
        raise MapError(source, len(lines), 1, "no start 'S' in the map")
    if not goals:
        raise MapError(source, len(lines), 1, "no goal 'G' in the map")
    ny = len(rows)
    # line li (1-based) is y = ny - li; column ci (1-based) is x = ci - 1
    occ = np.array(rows[::-1], dtype=bool).T.copy()  # [x, y]
    (sl, sc), (gl, gc) = starts[0], goals[0]
    return GridMap(occ, (sc - 1, ny - sl), (gc - 1, ny - gl), source)


def find_map(name: str | Path) -> Path:
    """The map file ``name``: as given (relative to the working directory), else under :data:`MAPS_DIR`
    (with or without ``.txt``). Raises ``FileNotFoundError`` naming what was tried."""
    p = Path(name)
    tried = [p]
    if p.is_file():
        return p
    for q in (MAPS_DIR / p, MAPS_DIR / p.name, MAPS_DIR / (p.name + ".txt")):
        tried.append(q)
        if q.is_file():
            return q
    raise FileNotFoundError(f"{name}: no such map file (looked in . and {MAPS_DIR})")


def load_map(path: str | Path) -> GridMap:
    """Read and parse a map file (found with :func:`find_map`); errors name the path as given."""
    p = find_map(path)
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise MapError(str(path), 1, 1, f"not UTF-8 text ({e.reason})") from None
    return parse_map(text, str(path))


def map_to_text(occupancy: np.ndarray, start: Cell | None = None, goal: Cell | None = None,
                virtual: np.ndarray | None = None) -> str:
    """The ASCII form of a grid (inverse of :func:`parse_map`); virtual obstacles, if given, as ``+``."""
    nx, ny = occupancy.shape
    out = []
    for y in range(ny - 1, -1, -1):
        row = []
        for x in range(nx):
            if (x, y) == start:
                row.append("S")
            elif (x, y) == goal:
                row.append("G")
            elif occupancy[x, y]:
                row.append("#")
            elif virtual is not None and virtual[x, y]:
                row.append("+")
            else:
                row.append(".")
        out.append("".join(row))
    return "\n".join(out) + "\n"


def check_cells(occupancy: np.ndarray, **cells: Cell) -> None:
    """Raise ``ValueError`` unless each named cell is on the grid and free."""
    if occupancy.ndim != 2 or occupancy.dtype != bool:
        raise ValueError(f"occupancy must be a 2-D boolean array, got {occupancy.dtype} {occupancy.shape}")
    nx, ny = occupancy.shape
    for name, (x, y) in cells.items():
        if not (0 <= x < nx and 0 <= y < ny):
            raise ValueError(f"{name} {(x, y)} is off the {nx} x {ny} grid")
        if occupancy[x, y]:
            raise ValueError(f"{name} {(x, y)} is an obstacle")


def closer_actions(cell: Cell, goal: Cell) -> tuple[int, ...]:
    """Section 3.2: the actions whose adjacent position is strictly nearer (Euclidean) to the goal."""
    x, y = cell
    gx, gy = goal
    d = math.hypot(x - gx, y - gy)
    return tuple(a for a, (dx, dy) in enumerate(ACTIONS) if math.hypot(x + dx - gx, y + dy - gy) < d)


def step_feasible(blocked3: np.ndarray, a: int, corner_cutting: bool = False) -> bool:
    """Can the robot at the centre of a 3 x 3 sensor reading (``blocked3[dx + 1, dy + 1]``, off-grid = True)
    take action ``a``? (The motion rule; the filling test uses cells only.)"""
    dx, dy = ACTIONS[a]
    if blocked3[1 + dx, 1 + dy]:
        return False
    if dx and dy and not corner_cutting and (blocked3[1 + dx, 1] or blocked3[1, 1 + dy]):
        return False
    return True


def current_position_actions(blocked3: np.ndarray, cell: Cell, goal: Cell) -> list[int]:
    """Section 3.2's "current position-action array": the actions whose adjacent position is nearer the
    goal and not an obstacle (``blocked3[dx + 1, dy + 1]``: the 3 x 3 sensor, real or virtual, off-grid = True)."""
    return [a for a in closer_actions(cell, goal) if not blocked3[1 + ACTIONS[a][0], 1 + ACTIONS[a][1]]]


def tends_to_concave(blocked3: np.ndarray, cell: Cell, goal: Cell) -> bool:
    """Section 3.2 / Algorithm 2 step (3): the current position-action array is empty, i.e. every
    position nearer the goal is infeasible, so ``cell`` possibly tends to a concave obstacle and is
    filled with a virtual obstacle. Never true at the goal (nothing is nearer than the goal itself)."""
    if tuple(cell) == tuple(goal):
        return False
    return not current_position_actions(blocked3, cell, goal)


def path_length(path) -> float:
    """Euclidean length of a cell path (1 per straight step, sqrt(2) per diagonal one)."""
    p = np.asarray(path, dtype=float).reshape(-1, 2)
    return float(np.hypot(*np.diff(p, axis=0).T).sum()) if len(p) > 1 else 0.0


class GridWorld:
    """An 8-connected grid with real and virtual obstacles, seen through a 3 x 3 sensor.

    Built from any boolean occupancy array (``[x, y]``), a start and a goal. Holds flat-index
    tables for a lean learning loop: ``nxt[s][a]`` (the successor, -1 off the grid) and
    ``ok[s][a]`` (the step is collision-free given real *and* virtual obstacles), both plain Python
    lists, and updates ``ok`` locally when :meth:`fill` adds a virtual obstacle.
    """

    def __init__(self, occupancy: np.ndarray, start: Cell, goal: Cell, corner_cutting: bool = False,
                 virtual: np.ndarray | None = None):
        occupancy = np.asarray(occupancy)
        check_cells(occupancy, start=start, goal=goal)
        self.occupancy = occupancy.copy()
        self.nx, self.ny = occupancy.shape
        self.start = (int(start[0]), int(start[1]))
        self.goal = (int(goal[0]), int(goal[1]))
        self.corner_cutting = bool(corner_cutting)
        self.virtual = np.zeros_like(occupancy) if virtual is None else (np.asarray(virtual, bool) & ~occupancy)
        self.virtual[self.goal] = False
        n = self.nx * self.ny
        self.n_states = n
        self.s_start = self.index(self.start)
        self.s_goal = self.index(self.goal)
        self.blocked: list[bool] = (self.occupancy | self.virtual).ravel().tolist()
        xs, ys = np.divmod(np.arange(n), self.ny)
        nxt = np.full((n, 8), -1, dtype=np.int64)
        for a, (dx, dy) in enumerate(ACTIONS):
            inside = (xs + dx >= 0) & (xs + dx < self.nx) & (ys + dy >= 0) & (ys + dy < self.ny)
            nxt[inside, a] = (xs[inside] + dx) * self.ny + ys[inside] + dy
        self.nxt: list[list[int]] = nxt.tolist()
        self.ok: list[list[bool]] = [self._ok_row(s) for s in range(n)]
        g = self.goal
        #: per state, the actions nearer the goal (section 3.2), precomputed
        self.closer: list[tuple[int, ...]] = [closer_actions(self.cell(s), g) for s in range(n)]
        #: states whose fill was taken back because it cut the start off from the goal. Fills only add
        #: obstacles, so such a fill would cut it off again: it is not tried (nor flood-filled) twice
        self.refused: set[int] = set()

    # -- cells and states
    def index(self, cell: Cell) -> int:
        return int(cell[0]) * self.ny + int(cell[1])

    def cell(self, s: int) -> Cell:
        return divmod(int(s), self.ny)

    def _blocked_at(self, x: int, y: int) -> bool:
        return not (0 <= x < self.nx and 0 <= y < self.ny) or self.blocked[x * self.ny + y]

    def _ok_row(self, s: int) -> list[bool]:
        x, y = divmod(s, self.ny)
        b = self._blocked_at
        row = []
        for dx, dy in ACTIONS:
            good = not b(x + dx, y + dy)
            if good and dx and dy and not self.corner_cutting:
                good = not (b(x + dx, y) or b(x, y + dy))
            row.append(good)
        return row

    # -- sensor and virtual obstacles
    def sense(self, s: int) -> np.ndarray:
        """The 3 x 3 sensor (section 4.2): ``blocked3[dx + 1, dy + 1]``, real or virtual obstacle or off-grid."""
        x, y = self.cell(s)
        return np.array([[self._blocked_at(x + dx, y + dy) for dy in (-1, 0, 1)] for dx in (-1, 0, 1)], dtype=bool)

    def tends_to_concave(self, s: int) -> bool:
        """Section 3.2 test at state ``s`` (fast path of :func:`tends_to_concave`)."""
        nxt, blocked = self.nxt[s], self.blocked
        closer = self.closer[s]
        return bool(closer) and not any(nxt[a] >= 0 and not blocked[nxt[a]] for a in closer)

    def fill(self, s: int) -> None:
        """Fill ``s`` with a virtual obstacle (Fig. 1(c)) and refresh the steps of its 3 x 3 neighbourhood."""
        if self.blocked[s] or s == self.s_goal:
            return
        self._set_virtual(s, True)

    def unfill(self, s: int) -> None:
        """Take the virtual obstacle at ``s`` away again."""
        x, y = self.cell(s)
        if self.virtual[x, y]:
            self._set_virtual(s, False)

    def connected(self, a: int | None = None, b: int | None = None) -> bool:
        """Can the robot walk from state ``a`` to ``b`` (default: start to goal) on the current grid?
        (Breadth-first flood fill over the allowed steps; not a path planner.)"""
        a = self.s_start if a is None else a
        b = self.s_goal if b is None else b
        seen = {a}
        todo = [a]
        nxt, ok = self.nxt, self.ok
        while todo:
            s = todo.pop()
            if s == b:
                return True
            for t, good in zip(nxt[s], ok[s]):
                if good and t not in seen:
                    seen.add(t)
                    todo.append(t)
        return False

    def _set_virtual(self, s: int, on: bool) -> None:
        x, y = self.cell(s)
        self.virtual[x, y] = on
        self.blocked[s] = on or bool(self.occupancy[x, y])
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if 0 <= x + dx < self.nx and 0 <= y + dy < self.ny:
                    t = (x + dx) * self.ny + y + dy
                    self.ok[t] = self._ok_row(t)

    def step_length(self, a: int) -> float:
        return STEP_LENGTH[a]
