"""Generated obstacle courses: a formation, a walled corridor, obstacles, a goal (``stack-fleet generate``).

``generate(seed, robots=None, formation=None, density=None)`` returns a scenario as data (the YAML of
``shared/spec/INTERFACES.md`` section 2), validated by :func:`stack.scenario.parse_scenario` and checked
solvable by :func:`unsolvable_reason` before it is returned. The same arguments give the same course;
every draw comes from ``numpy.random.default_rng(seed)``. ``docs/courses.md`` documents the families,
the density levels and the held-out seeds.

Layout: the leader starts at (0, 0) heading +x, the followers on their slots behind or beside it (up
to JITTER off); the goal is ``(length, 0)``; two corridor walls run at y = +-half_width from
behind the formation to past the goal. Obstacles sit in the *field*, x in [FIELD_START, length -
depth - GOAL_CLEAR] (depth: how far the formation reaches behind its leader), so the start and the
formation's final slots stay open.

Held-out seeds: :data:`HELDOUT_SEEDS` (1_000_000 .. 1_000_999) are for the held-out benchmark only
(``bench/heldout.py``); ``generate`` refuses them unless ``purpose="heldout"``, and refuses any other
seed with ``purpose="heldout"``. Training, tuning and tests use seeds 0 .. 999.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..scenario import Scenario, ScenarioError, parse_scenario

HELDOUT_START = 1_000_000
HELDOUT_SEEDS = range(HELDOUT_START, HELDOUT_START + 1000)
"""Seeds no training, tuning or test uses: the held-out benchmark's (``bench/heldout.py``)."""
TUNE_SEEDS = range(0, 1000)
"""Seeds for training, tuning and tests."""
PURPOSES = ("tune", "heldout")

RADIUS = 0.5  # robot radius [m] (Bai 2022 Table II)
V_MAX = 1.0  # [m/s]
W_MAX = 1.0  # [rad/s]
COMM_RANGE = 10.0  # [m]
CRUISE = 0.6  # the leader's cruise speed of pid and aina, a fraction of v_max: the time budget's basis
S_MIN, S_MAX = 2.0, 3.0  # nearest-neighbour spacing of a formation's robots [m]
L_MAX = 8.0  # no slot farther than this from the leader (inside the 10 m comm range with room to lag) [m]
MARGIN = 0.6  # solvable: a path 2 radius + MARGIN wide from every start to the goal [m]
GRID = 0.1  # the solvability check's grid [m]
FIELD_START = 6.0  # obstacles from this x on [m]
GOAL_CLEAR = 3.0  # no obstacle within this of the formation's final slots, along x [m]
LANE_CLEAR = 1.5  # `low`: free space beside the formation's straight lane [m]
MIN_FIELD = 8.0  # the field is at least this long [m] (16 m with a passage and a wall)
LENGTH = (30.0, 45.0)  # the goal's x when no length is given: uniform in this range [m]
CYLINDER_R = (0.4, 0.9)  # cylinder radius [m]
BOX_SIDE = (0.6, 2.0)  # box side lengths [m]; yaw uniform in [0, 180) deg
WALL_THICKNESS = 0.3  # cross walls [m]
NARROW_GAP = (2.0, 3.2)  # a narrow passage's gap [m]: wider than 2 radius + MARGIN, narrower than the formation
JITTER = 0.3  # followers start up to this far off their slots [m] (less where the spacing is tight)


class CourseError(ValueError):
    """A course that cannot be made with these arguments; ``str()`` is the one-line message."""


@dataclass(frozen=True)
class Density:
    """One obstacle density level."""

    per_10m: tuple[float, float]
    """Obstacles (cylinders and rotated boxes) per 10 m of field, drawn uniformly in this range."""
    gap: float
    """Least free space between two obstacles, an obstacle and a wall, or an obstacle and a cross wall [m]."""
    lane_free: bool
    """No obstacle in the formation's straight lane to the goal (width + LANE_CLEAR each side): a policy
    without avoidance (pid) passes."""
    walls: int
    """Cross walls with one gap the formation fits through unchanged (gap = width + 1..3 m)."""
    narrow: int
    """Narrow passages: two blocks across the corridor with a gap narrower than the formation (NARROW_GAP)."""


DENSITIES = {
    "low": Density(per_10m=(1.5, 2.5), gap=3.0, lane_free=True, walls=0, narrow=0),
    "medium": Density(per_10m=(2.5, 3.5), gap=2.6, lane_free=False, walls=1, narrow=0),
    "high": Density(per_10m=(3.0, 5.0), gap=2.2, lane_free=False, walls=1, narrow=1),
}

_C45 = math.sqrt(0.5)
_ARROW = ((3.0, 135.0), (3.0, -135.0), (4.0, 180.0), (5.0, 157.5), (5.0, -157.5))  # Bai 2022 Fig. 10 (case 1)


def _unit_points(family: str, n: int, side: int) -> list[tuple[float, float]]:
    """The followers' offsets in the leader's frame (x forward, y left), before scaling to the spacing."""
    k = range(1, n)
    if family == "wedge":  # a V behind the leader, arms at +-135 deg (Bai 2022's diamond front)
        return [(-((i + 1) // 2) * _C45, (1 if i % 2 else -1) * ((i + 1) // 2) * _C45) for i in k]
    if family == "line":  # line abreast, the leader in the middle
        return [(0.0, (1 if i % 2 else -1) * float((i + 1) // 2)) for i in k]
    if family == "column":  # single file behind the leader
        return [(-float(i), 0.0) for i in k]
    if family == "echelon":  # a diagonal to one side
        return [(-i * _C45, side * i * _C45) for i in k]
    if family == "diamond":
        return _diamond(n)
    if family == "triangle":  # Deng / Fan: equilateral rows behind the leader, outer robots first
        pts = []
        for r in range(1, 4):
            row = sorted((r / 2 - i for i in range(r + 1)), key=lambda y: (-abs(y), -y))
            pts += [(-r * math.sqrt(3) / 2, y) for y in row]
        return pts[: n - 1]
    if family == "arrow":  # Bai 2022 case 1's slots in the order they fill; 2.5 m between slots 1 and 2
        return [(L / 2.5 * math.cos(math.radians(p)), L / 2.5 * math.sin(math.radians(p))) for L, p in _ARROW[: n - 1]]
    raise CourseError(f"--formation: expected one of {', '.join(FAMILIES)}, got {family!r}")


def _diamond(n: int) -> list[tuple[float, float]]:
    """A rhombus lattice at 45 deg: 2 x 2 (Bai 2022's diamond) up to four robots, else the 3 x 3 ring."""
    cells = [(1, 0), (0, 1), (1, 1)] if n <= 4 else [(2, 0), (0, 2), (2, 2), (1, 0), (0, 1), (2, 1), (1, 2)]
    return [(-(i + j) * _C45, (i - j) * _C45) for i, j in cells[: n - 1]]


FAMILIES = ("wedge", "line", "diamond", "column", "echelon", "triangle", "arrow")


def spacing_range(family: str, n: int) -> tuple[float, float] | None:
    """(lowest, highest) nearest-neighbour spacing for ``n`` robots of ``family``, or None if it does not
    fit (a slot beyond L_MAX at the least spacing, or more robots than the family has places for)."""
    if n < 2:
        return None
    pts = _unit_points(family, n, 1)
    if len(pts) < n - 1:
        return None
    every = np.array([(0.0, 0.0), *pts])
    d = np.hypot(*(every[:, None, :] - every[None, :, :]).transpose(2, 0, 1))
    d_min = d[np.triu_indices(n, 1)].min()
    hi = min(S_MAX, L_MAX * d_min / np.hypot(every[:, 0], every[:, 1]).max())
    return (S_MIN, max(S_MIN, float(hi))) if hi >= S_MIN - 1e-9 else None


def families_for(n: int) -> list[str]:
    return [f for f in FAMILIES if spacing_range(f, n) is not None]


@dataclass(frozen=True)
class Course:
    """A generated course: the scenario as data and what the generator knows about it."""

    scenario: dict
    seed: int
    family: str
    robots: int
    density: str
    length: float  # the goal's x [m]
    spacing: float  # nearest-neighbour spacing of the formation [m]
    width: float  # the formation's width across the corridor, robots' bodies included [m]
    half_width: float  # the corridor's half width [m]
    obstacles: int  # cylinders and boxes in the field
    passages: tuple[dict, ...] = field(default=())  # {"x", "gap", "narrow", "kind"} per cross structure

    def header(self) -> str:
        """YAML comment lines describing the course (the CLI writes them above the scenario)."""
        pas = "; ".join(f"{p['kind']} at x = {p['x']:.1f} m, gap {p['gap']:.2f} m{' (narrow)' if p['narrow'] else ''}"
                        for p in self.passages) or "none"
        return (f"# generated by stack.fleet.courses: seed {self.seed}, {self.robots} robots in formation {self.family} "
                f"(spacing {self.spacing:.2f} m, width {self.width:.2f} m), density {self.density}\n"
                f"# corridor {2 * self.half_width:.1f} m wide, goal at x = {self.length:.1f} m, "
                f"{self.obstacles} obstacles; passages: {pas}\n")


def _check_seed(seed: int, purpose: str) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise CourseError(f"--seed: expected an integer >= 0, got {seed!r}")
    if purpose not in PURPOSES:
        raise CourseError(f"purpose: expected one of {', '.join(PURPOSES)}, got {purpose!r}")
    held = seed in HELDOUT_SEEDS
    if purpose == "tune" and held:
        raise CourseError(f"--seed {seed}: held out ({HELDOUT_SEEDS.start}..{HELDOUT_SEEDS.stop - 1} are for the "
                          "held-out benchmark only; train, tune and test on 0..999)")
    if purpose == "heldout" and not held:
        raise CourseError(f"--seed {seed}: not a held-out seed ({HELDOUT_SEEDS.start}..{HELDOUT_SEEDS.stop - 1})")


def _choose(rng: np.random.Generator, robots: int | None, family: str | None, density: str | None):
    """(robots, family, density): the given ones checked, the others drawn (every draw made either way):
    the family uniformly (among those that hold ``robots``), then the robot count among those it holds."""
    n_draw, f_draw, d_draw = rng.random(), rng.random(), str(rng.choice(list(DENSITIES)))
    if density is not None and density not in DENSITIES:
        raise CourseError(f"--density: expected one of {', '.join(DENSITIES)}, got {density!r}")
    if family is not None and family not in FAMILIES:
        raise CourseError(f"--formation: expected one of {', '.join(FAMILIES)}, got {family!r}")
    if robots is not None and (isinstance(robots, bool) or not isinstance(robots, (int, np.integer)) or not 3 <= robots <= 8):
        raise CourseError(f"--robots: expected 3..8, got {robots!r}")
    fams = [family] if family is not None else families_for(robots) if robots is not None else list(FAMILIES)
    family = fams[int(f_draw * len(fams))]
    fits = [m for m in range(3, 9) if spacing_range(family, m) is not None]
    if robots is None:
        robots = fits[int(n_draw * len(fits))]
    elif robots not in fits:
        raise CourseError(f"--robots {robots}: a {family} holds at most {max(fits)} robots (slots within {L_MAX:g} m "
                          f"of the leader at {S_MIN:g} m spacing)")
    return int(robots), family, density or d_draw


def _formation(rng: np.random.Generator, family: str, n: int) -> tuple[float, list[tuple[float, float]]]:
    """(spacing, follower offsets in metres)."""
    lo, hi = spacing_range(family, n)
    s = float(rng.uniform(lo, hi))
    side = 1 if rng.random() < 0.5 else -1
    pts = np.array(_unit_points(family, n, side))
    every = np.vstack([[0.0, 0.0], pts])
    d = np.hypot(*(every[:, None, :] - every[None, :, :]).transpose(2, 0, 1))
    scale = s / d[np.triu_indices(n, 1)].min()
    return s, [(float(x * scale), float(y * scale)) for x, y in pts]


def _r(x: float) -> float:
    return round(float(x), 3)


# --- layout ---------------------------------------------------------------------------------------


@dataclass
class _Field:
    """The free space the obstacles are placed in, and what they must keep clear of."""

    x0: float  # field from here ...
    x1: float  # ... to here along x [m]
    half_width: float  # corridor walls at y = +-half_width [m]
    lane: tuple[float, float] | None  # `low`: keep (y_lo, y_hi) free
    gap: float
    discs: list[tuple[float, float, float]] = field(default_factory=list)  # placed obstacles' bounding circles
    bars: list[tuple[float, float]] = field(default_factory=list)  # cross structures' x extents

    def fits(self, x: float, y: float, rb: float) -> bool:
        g = self.gap
        if abs(y) + rb > self.half_width - 0.1 - g or not (self.x0 + rb <= x <= self.x1 - rb):
            return False
        if self.lane is not None and not (y - rb >= self.lane[1] or y + rb <= self.lane[0]):
            return False
        if any(x + rb + g > a and x - rb - g < b for a, b in self.bars):
            return False
        return all(math.hypot(x - ox, y - oy) >= rb + orb + g for ox, oy, orb in self.discs)


def _obstacle(rng: np.random.Generator, fld: _Field) -> dict | None:
    """One cylinder or rotated box where it fits (None after 200 tries)."""
    for u in rng.random((200, 6)):
        x, y = fld.x0 + u[0] * (fld.x1 - fld.x0), (2 * u[1] - 1) * fld.half_width
        if u[2] < 0.5:
            r = CYLINDER_R[0] + u[3] * (CYLINDER_R[1] - CYLINDER_R[0])
            if fld.fits(x, y, r):
                fld.discs.append((x, y, r))
                return {"type": "cylinder", "x": _r(x), "y": _r(y), "radius": _r(r)}
        else:
            sx, sy = (BOX_SIDE[0] + v * (BOX_SIDE[1] - BOX_SIDE[0]) for v in u[3:5])
            rb = math.hypot(sx, sy) / 2
            if fld.fits(x, y, rb):
                fld.discs.append((x, y, rb))
                return {"type": "box", "x": _r(x), "y": _r(y), "size_x": _r(sx), "size_y": _r(sy), "yaw_deg": _r(180 * u[5])}
    return None


def _gap_centre(rng: np.random.Generator, gap: float, h: float, most: float) -> float:
    a = max(0.0, min(most, h - 1.0 - gap / 2))
    return float(rng.uniform(-a, a))


def _wall_with_gap(rng: np.random.Generator, x: float, h: float, width: float) -> tuple[list[dict], dict, tuple]:
    """A cross wall with one gap the formation fits through unchanged."""
    gap = float(min(rng.uniform(width + 1.0, width + 3.0), 2 * h - 2.0))
    yc = _gap_centre(rng, gap, h, h)
    lo, hi = yc - gap / 2, yc + gap / 2
    walls = [{"type": "wall", "from": [_r(x), _r(-h)], "to": [_r(x), _r(lo)], "thickness": WALL_THICKNESS},
             {"type": "wall", "from": [_r(x), _r(hi)], "to": [_r(x), _r(h)], "thickness": WALL_THICKNESS}]
    return walls, {"kind": "wall", "x": x, "gap": gap, "narrow": gap < width}, (x - WALL_THICKNESS / 2, x + WALL_THICKNESS / 2)


def _narrow_passage(rng: np.random.Generator, x: float, h: float, width: float) -> tuple[list[dict], dict, tuple]:
    """Two blocks across the corridor; the gap between them is narrower than the formation where it can be
    (NARROW_GAP; a formation narrower than NARROW_GAP[0] + 0.3 m, a column, gets the least gap)."""
    top = min(NARROW_GAP[1], width - 0.3)
    gap = float(rng.uniform(NARROW_GAP[0], top)) if top > NARROW_GAP[0] else NARROW_GAP[0]
    length = float(rng.uniform(1.0, 3.0))
    yc = _gap_centre(rng, gap, h, 3.0)
    lo, hi = yc - gap / 2, yc + gap / 2
    blocks = [{"type": "box", "x": _r(x), "y": _r((hi + h) / 2), "size_x": _r(length), "size_y": _r(h - hi), "yaw_deg": 0.0},
              {"type": "box", "x": _r(x), "y": _r((lo - h) / 2), "size_x": _r(length), "size_y": _r(lo + h), "yaw_deg": 0.0}]
    return blocks, {"kind": "passage", "x": x, "gap": gap, "narrow": gap < width}, (x - length / 2, x + length / 2)


def _layout(rng: np.random.Generator, dens: Density, fld: _Field, width: float) -> tuple[list[dict], list[dict], int]:
    """(obstacles, passages, least count of field obstacles): cross structures first, then cylinders and
    boxes, as many as drawn from ``per_10m`` or as fit with the density's gap (at least the range's low end)."""
    z = fld.x1 - fld.x0
    spots = []
    if dens.narrow:
        spots.append((_narrow_passage, fld.x0 + z * rng.uniform(0.25, 0.35)))
    if dens.walls:
        spots.append((_wall_with_gap, fld.x0 + z * (rng.uniform(0.65, 0.75) if dens.narrow else rng.uniform(0.35, 0.65))))
    obstacles, passages = [], []
    for make, x in spots:
        obs, info, bar = make(rng, float(x), fld.half_width, width)
        obstacles += obs
        passages.append(info | {"x": _r(info["x"]), "gap": _r(info["gap"])})
        fld.bars.append(bar)
    least = max(1, round(dens.per_10m[0] * z / 10.0))
    for _ in range(max(least, round(rng.uniform(*dens.per_10m) * z / 10.0))):
        o = _obstacle(rng, fld)
        if o is None:
            break
        obstacles.append(o)
    return obstacles, passages, least


def time_budget(length: float, v_max: float = V_MAX) -> float:
    """`duration` and `success.max_time` [s]: twice the leader's time at the cruise speed of pid and aina
    (CRUISE v_max) plus 20 s, rounded up to 10 s."""
    return float(math.ceil((2.0 * length / (CRUISE * v_max) + 20.0) / 10.0) * 10)


def _scenario(seed: int, name: str, offsets: list, starts: list, length: float, h: float, obstacles: list,
              density: str) -> dict:
    depth = max([0.0] + [-x for x, _ in offsets])
    corridor = [{"type": "wall", "from": [_r(-depth - 4.0), y], "to": [_r(length + 5.0), y], "thickness": 0.2}
                for y in (_r(h), _r(-h))]
    t = time_budget(length)
    slots = {k: {"L": _r(math.hypot(x, y)), "psi_deg": _r(math.degrees(math.atan2(y, x)))}
             for k, (x, y) in enumerate(offsets, 1)}
    robots = [{"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0]}]
    robots += [{"id": k, "role": "follower", "pose": [_r(x), _r(y), _r(yaw)]} for k, (x, y, yaw) in enumerate(starts, 1)]
    policies = ["drl", "aina", "qlearn", "fuzzy"] + (["pid"] if DENSITIES[density].lane_free else [])
    return {
        "name": name, "seed": int(seed), "dt": 0.1, "duration": t,
        "world": {"obstacles": corridor + obstacles},
        "robot": {"radius": RADIUS, "v_max": V_MAX, "w_max": W_MAX,
                  "lidar": {"beams": 180, "fov_deg": 180, "range": 5.0, "noise_std": 0.01}, "comm_range": COMM_RANGE},
        "comm": {"loss": 0.0, "latency_ms": 0},
        "formation": {"leader": 0, "goal": [_r(length), 0.0], "slots": slots},
        "robots": robots,
        "success": {"goal_tolerance": 0.5, "max_time": t, "no_collisions": True},
        "bench": {"policies": policies, "reference": f"generated course (stack.fleet.courses), seed {seed}, density {density}"},
    }


def _starts(rng: np.random.Generator, offsets: list, spacing: float) -> list[tuple[float, float, float]]:
    """Followers a little off their slots (at most (spacing - 2 radius - MARGIN) / 2 each, so starts keep
    2 radius + MARGIN apart) and up to 10 deg off the course's heading."""
    most = min(JITTER, (spacing - 2 * RADIUS - MARGIN) / 2)
    out = []
    for x, y in offsets:
        r, a = most * math.sqrt(rng.random()), rng.uniform(-math.pi, math.pi)
        out.append((x + r * math.cos(a), y + r * math.sin(a), float(rng.uniform(-10.0, 10.0))))
    return out


def generate_course(seed: int, robots: int | None = None, formation: str | None = None, density: str | None = None,
                    length: float | None = None, purpose: str = "tune") -> Course:
    """The course of ``seed`` (the arguments not given are drawn from it); see the module's docstring."""
    _check_seed(seed, purpose)
    rng = np.random.default_rng(int(seed))
    n, family, dname = _choose(rng, robots, formation, density)
    dens = DENSITIES[dname]
    spacing, offsets = _formation(rng, family, n)
    ys = [0.0] + [y for _, y in offsets]
    width = max(ys) - min(ys) + 2 * RADIUS
    depth = max([0.0] + [-x for x, _ in offsets])
    need = depth + GOAL_CLEAR + FIELD_START + MIN_FIELD * (2 if dens.narrow else 1)
    drawn = float(rng.uniform(*LENGTH))
    if length is None:
        length = max(drawn, need)
    elif not (isinstance(length, (int, float)) and need <= length <= 200.0):
        raise CourseError(f"--length: a {family} of {n} at density {dname} needs {need:.1f}..200 m, got {length!r}")
    length = _r(length)
    flank = LANE_CLEAR + dens.gap + 3.0 if dens.lane_free else 4.0  # `low`: room for obstacles beside the lane
    h = math.ceil(2 * max(7.0, max(abs(y) for y in ys) + RADIUS + flank)) / 2
    lane = (min(ys) - RADIUS - LANE_CLEAR, max(ys) + RADIUS + LANE_CLEAR) if dens.lane_free else None
    name = f"course-{seed}-{family}{n}-{dname}"
    reason = ""
    for _ in range(20):
        fld = _Field(FIELD_START, length - depth - GOAL_CLEAR, h, lane, dens.gap)
        obstacles, passages, want = _layout(rng, dens, fld, width)
        data = _scenario(seed, name, offsets, _starts(rng, offsets, spacing), length, h, obstacles, dname)
        placed = len(fld.discs)
        reason = (f"{placed} of {want} obstacles fit" if placed < want
                  else unsolvable_reason(parse_scenario(data, f"<course seed {seed}>")))
        if not reason:
            return Course(data, int(seed), family, n, dname, length, _r(spacing), _r(width), h, placed, tuple(passages))
    raise CourseError(f"--seed {seed}: no solvable layout in 20 tries ({reason})")


def generate(seed: int, robots: int | None = None, formation: str | None = None, density: str | None = None,
             length: float | None = None, purpose: str = "tune") -> dict:
    """The scenario of :func:`generate_course` as data (validated and checked solvable)."""
    return generate_course(seed, robots, formation, density, length, purpose).scenario


def random_scenarios(n: int, first_seed: int = 0, robots: int | None = None, formation: str | None = None,
                     density: str | None = None, purpose: str = "tune") -> list[Course]:
    """Courses of seeds first_seed .. first_seed + n - 1 (``stack-fleet bench --random N``)."""
    if n < 1:
        raise CourseError(f"--random: expected at least 1 course, got {n}")
    return [generate_course(s, robots, formation, density, purpose=purpose) for s in range(first_seed, first_seed + n)]


def write_course(course: Course, path: Path) -> Path:
    """The course's scenario as YAML under its header comment (an arrival task's too)."""
    import yaml

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(course.header() + yaml.safe_dump(course.scenario, sort_keys=False))
    return path


# --- solvability ----------------------------------------------------------------------------------


def distance_field(obstacles, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Distance [m] from each point (x, y) to the nearest obstacle surface (negative inside one)."""
    d = np.full(np.shape(x), np.inf)
    for o in obstacles:
        if o.type == "cylinder":
            d = np.minimum(d, np.hypot(x - o.x, y - o.y) - o.radius)
            continue
        cx, cy, hx, hy, yaw = o.as_box()
        c, s = math.cos(yaw), math.sin(yaw)
        qx = np.abs((x - cx) * c + (y - cy) * s) - hx
        qy = np.abs(-(x - cx) * s + (y - cy) * c) - hy
        d = np.minimum(d, np.hypot(np.maximum(qx, 0), np.maximum(qy, 0)) + np.minimum(np.maximum(qx, qy), 0))
    return d


def _extent(o) -> tuple[float, float, float, float]:
    if o.type == "cylinder":
        return o.x - o.radius, o.x + o.radius, o.y - o.radius, o.y + o.radius
    cx, cy, hx, hy, yaw = o.as_box()
    ex = abs(hx * math.cos(yaw)) + abs(hy * math.sin(yaw))
    ey = abs(hx * math.sin(yaw)) + abs(hy * math.cos(yaw))
    return cx - ex, cx + ex, cy - ey, cy + ey


def label_free(free: np.ndarray) -> np.ndarray:
    """Connected components (4-neighbour) of the True cells; -1 on the others. Runs along axis 1 per
    index of axis 0, joined by union-find where runs of neighbouring indices overlap."""
    pad = np.zeros((free.shape[0], free.shape[1] + 2), np.int8)
    pad[:, 1:-1] = free
    ri, rj = np.nonzero(np.diff(pad, axis=1))  # row-major: each run's start, then its end
    runs = list(zip(ri[::2].tolist(), rj[::2].tolist(), rj[1::2].tolist()))
    parent = list(range(len(runs)))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    first = np.searchsorted(ri[::2], np.arange(free.shape[0] + 1))  # runs of index i: first[i] .. first[i + 1]
    for i in range(free.shape[0] - 1):
        a, a_end, b, b_end = first[i], first[i + 1], first[i + 1], first[i + 2]
        while a < a_end and b < b_end:
            (_, plo, phi), (_, clo, chi) = runs[a], runs[b]
            if plo < chi and clo < phi:
                parent[find(a)] = find(b)
            if phi <= chi:
                a += 1
            else:
                b += 1
    labels = np.full(free.shape, -1, dtype=np.int64)
    for k, (i, lo, hi) in enumerate(runs):
        labels[i, lo:hi] = find(k)
    return labels


def free_cells(obstacles, xs: np.ndarray, ys: np.ndarray, clearance: float) -> np.ndarray:
    """Cells (xs x ys centres) farther than ``clearance`` from every obstacle; each obstacle is looked at
    only in the window of its extent grown by ``clearance``."""
    free = np.ones((xs.size, ys.size), bool)
    res_x, res_y = xs[1] - xs[0], ys[1] - ys[0]
    for o in obstacles:
        ax, bx, ay, by = _extent(o)
        i0, i1 = (int(np.clip(math.floor((v - xs[0]) / res_x), 0, xs.size)) for v in (ax - clearance, bx + clearance + 2 * res_x))
        j0, j1 = (int(np.clip(math.floor((v - ys[0]) / res_y), 0, ys.size)) for v in (ay - clearance, by + clearance + 2 * res_y))
        if i0 < i1 and j0 < j1:
            gx, gy = np.meshgrid(xs[i0:i1], ys[j0:j1], indexing="ij")
            free[i0:i1, j0:j1] &= distance_field([o], gx, gy) > clearance
    return free


def _targets(sc: Scenario) -> list[tuple[str, tuple[float, float], tuple[float, float]]]:
    """(who, start, goal) per robot: the leader to the formation's goal, each follower to its final slot
    around it; an arrival-time peer to its own goal."""
    out = []
    f = sc.formation
    for r in sc.robots:
        if f is None:
            goal = r.goal
        elif r.id == f.leader:
            goal = f.goal
        else:
            s = f.final_slots[r.id]
            goal = (f.goal[0] + s.L * math.cos(s.psi), f.goal[1] + s.L * math.sin(s.psi))
        out.append((f"robot {r.id}", (r.pose[0], r.pose[1]), (float(goal[0]), float(goal[1]))))
    return out


def _grid(sc: Scenario, points: list[tuple[float, float]], res: float) -> tuple[np.ndarray, np.ndarray]:
    """Cell centres over the starts and goals (3 m around) and the obstacles, at most 20 m beyond the
    starts and goals: paths leave neither."""
    px, py = [p[0] for p in points], [p[1] for p in points]
    lo_x, hi_x, lo_y, hi_y = min(px) - 3, max(px) + 3, min(py) - 3, max(py) + 3
    for o in sc.obstacles:
        ax, bx, ay, by = _extent(o)
        lo_x, hi_x, lo_y, hi_y = min(lo_x, ax), max(hi_x, bx), min(lo_y, ay), max(hi_y, by)
    lo_x, hi_x = max(lo_x, min(px) - 20), min(hi_x, max(px) + 20)
    lo_y, hi_y = max(lo_y, min(py) - 20), min(hi_y, max(py) + 20)
    return np.arange(lo_x, hi_x + res / 2, res), np.arange(lo_y, hi_y + res / 2, res)


def unsolvable_reason(sc: Scenario, margin: float = MARGIN, res: float = GRID) -> str | None:
    """None if the course is solvable, else why not (one line).

    Solvable: every start at least radius + margin / 2 from every obstacle, the starts 2 radius + margin
    apart, and a path at least 2 radius + margin wide from every robot's start to its goal (the leader's:
    formation.goal; a follower's: its final slot there): on a grid of ``res``, obstacles inflated by
    radius + margin / 2 + res / 2 (so that what joins two cell centres keeps that clearance too), every
    start and goal in the leader's start's 4-connected free component."""
    radius = max(r.radius for r in sc.robots)
    need = radius + margin / 2
    tasks = _targets(sc)
    starts = np.array([s for _, s, _ in tasks])
    clear = distance_field(sc.obstacles, starts[:, 0], starts[:, 1])
    for (who, _, _), c in zip(tasks, clear):
        if c < need:
            return f"{who} starts {c:.2f} m from an obstacle (needs {need:.2f} m)"
    for i in range(len(tasks)):
        for j in range(i + 1, len(tasks)):
            d = math.dist(tasks[i][1], tasks[j][1])
            if d < 2 * radius + margin:
                return f"{tasks[i][0]} and {tasks[j][0]} start {d:.2f} m apart (need {2 * radius + margin:.2f} m)"
    xs, ys = _grid(sc, [p for _, s, g in tasks for p in (s, g)], res)
    labels = label_free(free_cells(sc.obstacles, xs, ys, need + res / 2))

    def label(p):
        return labels[int(round((p[0] - xs[0]) / res)), int(round((p[1] - ys[0]) / res))]

    home = label(tasks[0][1])
    for who, s, g in tasks:
        if label(s) < 0 or label(s) != home:
            return f"{who} has no room to move at its start ({s[0]:.1f}, {s[1]:.1f})"
        if label(g) != home:
            return f"no path {2 * need:.2f} m wide from {who}'s start to its goal ({g[0]:.1f}, {g[1]:.1f})"
    return None


# --- command line ---------------------------------------------------------------------------------


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        print(f"{self.prog}: {message}", file=sys.stderr)
        sys.exit(2)


def parser(prog: str = "python -m stack.fleet.courses") -> argparse.ArgumentParser:
    from ..argtypes import nonnegative_int

    ap = _Parser(prog=prog, description="Write a generated, solvable obstacle course as a scenario file.")
    ap.add_argument("--seed", type=nonnegative_int, required=True, help="the course's seed (0..999 for tuning and tests)")
    ap.add_argument("--robots", type=int, help="3..8 (default: drawn from the seed)")
    ap.add_argument("--formation", help=f"{', '.join(FAMILIES)} (default: drawn)")
    ap.add_argument("--density", help=f"{', '.join(DENSITIES)} (default: drawn)")
    ap.add_argument("--length", type=float, help="the goal's x [m] (default: drawn in 30..45)")
    ap.add_argument("--heldout", action="store_true",
                    help=f"the seed is a held-out one ({HELDOUT_SEEDS.start}..{HELDOUT_SEEDS.stop - 1}): benchmarks only")
    ap.add_argument("--out", type=Path, required=True, help="scenario file to write")
    return ap


def generate_to_file(prog: str, out: Path, make):
    """``make()`` (a :class:`Course` or anything with ``scenario`` and ``header()``), written to ``out``; None
    after one line on stderr naming what is wrong (the caller exits 2)."""
    try:
        if out.is_dir():
            raise CourseError(f"--out {out}: is a folder (give a file name)")
        made = make()
        write_course(made, out)
        return made
    except (CourseError, ScenarioError, OSError) as e:
        print(f"{prog}: {f'--out {out}: {e.strerror or e}' if isinstance(e, OSError) else e}", file=sys.stderr)
        return None


def main(argv: list[str] | None = None, prog: str = "python -m stack.fleet.courses") -> int:
    a = parser(prog).parse_args(argv)
    course = generate_to_file(prog, a.out, lambda: generate_course(a.seed, a.robots, a.formation, a.density, a.length,
                                                                   purpose="heldout" if a.heldout else "tune"))
    if course is None:
        return 2
    print(f"{a.out}: {course.robots} robots, {course.family}, density {course.density}, goal at x = {course.length:g} m, "
          f"{course.obstacles} obstacles, {len(course.passages)} passages; max_time {course.scenario['duration']:g} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
