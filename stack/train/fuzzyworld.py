"""A fast numpy world for Chang 2020's PSO fitness evaluations (and quick checks of the policy).

Unicycle robots (v clipped to [0, v_max], w to +-w_max, exact arcs), static obstacles (boxes as
four segments, circles), a lidar of ``beams`` rays over ``fov`` cast analytically against segments,
circles and the other robots (discs), optional range noise, and a radio with per-message loss.
Each robot's policy sees the same :class:`stack.policies.base.Observation` the agent builds, by the
same code (:mod:`stack.models.observation`; own pose exact here: ground truth stands in for the
estimate), and moves by the same exact arc (:mod:`stack.models.kinematics`), so the trained
parameters are the ones the fleet runs. A collision is centre distance < 2 r (robots) or < r to an obstacle
surface (the contract's definitions); arrivals are the first step within ``goal_tol`` of the goal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..models.kinematics import arc_step_array
from ..models.observation import STALE_AFTER_S, neighbour_view, observation_fields
from ..policies.base import Observation


@dataclass
class World:
    boxes: list[tuple[float, float, float, float, float]] = field(default_factory=list)  # cx, cy, hx, hy, yaw
    circles: list[tuple[float, float, float]] = field(default_factory=list)  # cx, cy, r

    def __post_init__(self):
        segs = []
        for cx, cy, hx, hy, yaw in self.boxes:
            c, s = math.cos(yaw), math.sin(yaw)
            pts = [(cx + c * px - s * py, cy + s * px + c * py) for px, py in ((hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy))]
            segs += [(*pts[k], *pts[(k + 1) % 4]) for k in range(4)]
        self.segs = np.array(segs, float).reshape(-1, 4)
        self.circ = np.array(self.circles, float).reshape(-1, 3)
        self._boxes = np.array(self.boxes, float).reshape(-1, 5)

    @classmethod
    def from_scenario(cls, sc) -> "World":
        boxes, circles = [], []
        for o in sc.obstacles:
            if o.type == "cylinder":
                circles.append((o.x, o.y, o.radius))
            else:
                boxes.append(o.as_box())
        return cls(boxes, circles)

    def surface_distance(self, x: float, y: float) -> float:
        """Centre -> nearest obstacle surface (negative inside)."""
        d = math.inf
        for cx, cy, hx, hy, yaw in self._boxes:
            c, s = math.cos(yaw), math.sin(yaw)
            px, py = c * (x - cx) + s * (y - cy), -s * (x - cx) + c * (y - cy)
            qx, qy = abs(px) - hx, abs(py) - hy
            out = math.hypot(max(qx, 0.0), max(qy, 0.0))
            d = min(d, out if (qx > 0 or qy > 0) else max(qx, qy))
        if len(self.circ):
            d = min(d, float((np.hypot(self.circ[:, 0] - x, self.circ[:, 1] - y) - self.circ[:, 2]).min()))
        return d


def ray_cast(ox: float, oy: float, ang: np.ndarray, segs: np.ndarray, circ: np.ndarray, rmax: float) -> np.ndarray:
    """Range along each angle [rad, world] from (ox, oy) to the first segment or circle, at most rmax."""
    dx, dy = np.cos(ang)[:, None], np.sin(ang)[:, None]
    r = np.full(ang.shape, rmax)
    if len(segs):
        ax, ay, bx, by = (segs[:, k][None, :] for k in range(4))
        ex, ey = bx - ax, by - ay
        den = dx * ey - dy * ex
        wx, wy = ax - ox, ay - oy
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wx * ey - wy * ex) / den
            u = (wx * dy - wy * dx) / den
        t = np.where((np.abs(den) > 1e-12) & (u >= 0) & (u <= 1) & (t > 0), t, np.inf)
        r = np.minimum(r, t.min(axis=1))
    if len(circ):
        cx, cy, cr = (circ[:, k][None, :] for k in range(3))
        px, py = cx - ox, cy - oy
        b = dx * px + dy * py
        disc = b * b - (px * px + py * py - cr * cr)
        sq = np.sqrt(np.maximum(disc, 0.0))
        t1, t2 = b - sq, b + sq
        t = np.where(t1 > 0, t1, np.where(t2 > 0, 0.0, np.inf))  # inside a circle: range 0
        t = np.where(disc >= 0, t, np.inf)
        r = np.minimum(r, t.min(axis=1))
    return r


@dataclass
class RobotSpec:
    pose: tuple[float, float, float]  # x, y, yaw [rad]
    goal: tuple[float, float]


@dataclass
class SimConfig:
    dt: float = 0.1
    radius: float = 0.3
    v_max: float = 1.0
    w_max: float = 1.5
    beams: int = 40
    fov: float = math.pi
    range_max: float = 5.0
    noise_std: float = 0.0
    comm_range: float = 150.0
    loss: float = 0.0
    goal_tol: float = 0.5
    max_steps: int = 3000


@dataclass
class RunResult:
    arrivals: list[int | None]  # step of first arrival per robot
    collisions_robot: int
    collisions_obstacle: int
    min_obstacle: float
    min_robot: float
    steps: int
    traj: np.ndarray | None = None  # (steps, n, 3)

    @property
    def spread(self) -> int | None:
        a = self.arrivals
        return None if any(x is None for x in a) else int(max(a) - min(a))

    @property
    def complete(self) -> int | None:
        a = self.arrivals
        return None if any(x is None for x in a) else int(max(a))


class _Radio:
    """What each robot last heard of each other one (per-message loss, within ``comm_range``)."""

    def __init__(self, n: int):
        # receiver -> sender -> (x, y, yaw, v, w, stamp [s], d_goal) as last delivered
        self.last: list[list[tuple | None]] = [[None] * n for _ in range(n)]

    def reports(self, i: int, k: int, st: np.ndarray, vw: np.ndarray, goals: np.ndarray, cfg: SimConfig,
                rng: np.random.Generator) -> list[tuple]:
        """Robot i's reports at step k, (x, y, yaw, v, w, age, d_goal) each, stamped and aged on the
        step clock k dt as the agent stamps and ages them; those older than STALE_AFTER_S left out."""
        now, out = k * cfg.dt, []
        for j in range(len(st)):
            if j == i:
                continue
            d = math.hypot(st[j, 0] - st[i, 0], st[j, 1] - st[i, 1])
            if d <= cfg.comm_range and rng.random() >= cfg.loss:
                self.last[i][j] = (st[j, 0], st[j, 1], st[j, 2], vw[j, 0], vw[j, 1], now,
                                   math.hypot(goals[j, 0] - st[j, 0], goals[j, 1] - st[j, 1]))
            h = self.last[i][j]
            if h is not None and now - h[5] <= STALE_AFTER_S:
                out.append((*h[:5], now - h[5], h[6]))
        return out


def observe(pose: np.ndarray, vw: np.ndarray, goal: tuple[float, float], reports: list[tuple], scan: np.ndarray,
            cfg: SimConfig) -> Observation:
    """Robot's Observation from its pose (x, y, yaw; exact here), its (v, w), its goal, its neighbours' reports
    and one scan: :func:`stack.models.observation.observation_fields`, the agent's decision layer's builder."""
    x, y, yaw = (float(a) for a in pose)
    view = neighbour_view((x, y), yaw, reports, cfg.comm_range)
    return Observation(**observation_fields(x, y, yaw, float(vw[0]), float(vw[1]), (float(goal[0]), float(goal[1])),
                                            view, scans=scan[None, :], scan_range=cfg.range_max, dt=cfg.dt))


def _scan(i: int, st: np.ndarray, world: World, rel: np.ndarray, cfg: SimConfig, rng: np.random.Generator) -> np.ndarray:
    """Robot i's lidar: the obstacles and the other robots (discs), optional range noise."""
    others = np.array([(st[j, 0], st[j, 1], cfg.radius) for j in range(len(st)) if j != i]).reshape(-1, 3)
    circ = np.vstack([world.circ, others]) if len(others) else world.circ
    scan = ray_cast(st[i, 0], st[i, 1], st[i, 2] + rel, world.segs, circ, cfg.range_max)
    if cfg.noise_std > 0:
        scan = np.clip(scan + rng.normal(0, cfg.noise_std, scan.shape), 0.0, cfg.range_max)
    return scan


@dataclass
class _Contacts:
    """Collisions (counted once per contact: a rising edge) and the closest approaches of a run."""

    robot: int = 0
    obstacle: int = 0
    min_obstacle: float = math.inf
    min_robot: float = math.inf
    touching: set = field(default_factory=set)  # robot i (obstacle) or pair (i, j) (robots) in contact now

    def _edge(self, key, now: bool) -> int:
        new = now and key not in self.touching
        (self.touching.add if now else self.touching.discard)(key)
        return int(new)

    def update(self, st: np.ndarray, world: World, cfg: SimConfig) -> None:
        n = len(st)
        for i in range(n):
            so = world.surface_distance(st[i, 0], st[i, 1])
            self.min_obstacle = min(self.min_obstacle, so)
            self.obstacle += self._edge(i, so < cfg.radius)
            for j in range(i + 1, n):
                dr = math.hypot(st[i, 0] - st[j, 0], st[i, 1] - st[j, 1])
                self.min_robot = min(self.min_robot, dr)
                self.robot += self._edge((i, j), dr < 2 * cfg.radius)


def run(world: World, robots: list[RobotSpec], policies: list, cfg: SimConfig | None = None, *, seed: int = 0,
        record: bool = False, stop_on_collision: bool = False) -> RunResult:
    """All robots to their goals (until every robot has arrived or ``max_steps``)."""
    cfg = cfg or SimConfig()
    rng = np.random.default_rng(seed)
    n = len(robots)
    st = np.array([r.pose for r in robots], float)
    vw = np.zeros((n, 2))
    goals = np.array([r.goal for r in robots], float)
    rel = np.linspace(-cfg.fov / 2, cfg.fov / 2, cfg.beams)
    radio, contacts = _Radio(n), _Contacts()
    arrivals: list[int | None] = [None] * n
    traj = [] if record else None
    for p in policies:
        p.reset()
    k = 0
    for k in range(cfg.max_steps):
        for i in range(n):
            scan = _scan(i, st, world, rel, cfg, rng)
            obs = observe(st[i], vw[i], goals[i], radio.reports(i, k, st, vw, goals, cfg, rng), scan, cfg)
            v, w = policies[i].act(obs)
            vw[i] = (min(max(v, 0.0), cfg.v_max), min(max(w, -cfg.w_max), cfg.w_max))
        st[:, 0], st[:, 1], st[:, 2] = arc_step_array(st[:, 0], st[:, 1], st[:, 2], vw[:, 0], vw[:, 1], cfg.dt)
        if record:
            traj.append(st.copy())
        contacts.update(st, world, cfg)
        for i in range(n):
            if arrivals[i] is None and math.hypot(st[i, 0] - goals[i, 0], st[i, 1] - goals[i, 1]) <= cfg.goal_tol:
                arrivals[i] = k + 1
        if all(a is not None for a in arrivals) or (stop_on_collision and (contacts.robot or contacts.obstacle)):
            break
    return RunResult(arrivals, contacts.robot, contacts.obstacle, contacts.min_obstacle, contacts.min_robot, k + 1,
                     np.array(traj) if record else None)


def sectors_world(x: float, y: float, yaw: float, world: World, cfg: SimConfig) -> np.ndarray:
    """One robot's scan in ``world`` (for phase 1, no other robots)."""
    rel = np.linspace(-cfg.fov / 2, cfg.fov / 2, cfg.beams)
    return ray_cast(x, y, yaw + rel, world.segs, world.circ, cfg.range_max)


# -- the training environments ----------------------------------------------------------------
def phase1_world() -> World:
    """Fig. 6 in spirit: one object with straight sides, outer and inner corners (perimeter ~ 62 m)."""
    return World(boxes=[(0.0, 0.0, 6.0, 2.0, 0.0), (3.0, 4.0, 2.0, 3.0, 0.0), (-4.0, -3.5, 1.5, 2.0, 0.0)],
                 circles=[(-6.5, 1.0, 1.0)])


def phase1_start() -> tuple[float, float, float]:
    """0.8 m south of the object's south face (y = -2), heading east: the object is on the left."""
    return (0.0, -2.8, 0.0)


def phase2_task() -> tuple[World, list[RobotSpec]]:
    """Fig. 7 in spirit: three robots 30.4, 39.5, 43.8 m from the target (-11, -23), blocks between."""
    target = (-11.0, -23.0)
    starts = [(-11.0 + 30.4 * math.cos(a), -23.0 + 30.4 * math.sin(a)) for a in [math.radians(80)]]
    starts += [(-11.0 + 39.5 * math.cos(math.radians(30)), -23.0 + 39.5 * math.sin(math.radians(30)))]
    starts += [(-11.0 + 43.8 * math.cos(math.radians(125)), -23.0 + 43.8 * math.sin(math.radians(125)))]
    boxes = [(-11.0 + 12 * math.cos(math.radians(80)) + 0.5, -23.0 + 12 * math.sin(math.radians(80)), 2.5, 1.5, 0.3),
             (-11.0 + 20 * math.cos(math.radians(30)), -23.0 + 20 * math.sin(math.radians(30)), 2.0, 2.0, 0.0),
             (-11.0 + 25 * math.cos(math.radians(125)), -23.0 + 25 * math.sin(math.radians(125)), 3.0, 1.5, 0.6),
             (-11.0 + 8 * math.cos(math.radians(45)), -23.0 + 8 * math.sin(math.radians(45)), 1.5, 1.0, 0.0),
             (-11.0 + 32 * math.cos(math.radians(100)), -23.0 + 32 * math.sin(math.radians(100)), 2.0, 2.0, 0.2)]
    goals = arrival_goals(target, 3)
    robots = [RobotSpec((sx, sy, math.atan2(target[1] - sy, target[0] - sx)), g) for (sx, sy), g in zip(starts, goals)]
    return World(boxes=boxes), robots


def radial_task(target, dists, angles_deg, blocks) -> tuple[World, list[RobotSpec]]:
    """Robots ``dists`` from ``target`` along ``angles_deg``, heading at it; ``blocks`` (f, offset, hx, hy,
    yaw_deg, k): a box on robot k's line at fraction f of its distance, ``offset`` metres to the side."""
    boxes = []
    for f, off, hx, hy, yaw, k in blocks:
        a, d = math.radians(angles_deg[k]), dists[k]
        boxes.append((target[0] + f * d * math.cos(a) - off * math.sin(a), target[1] + f * d * math.sin(a) + off * math.cos(a),
                      hx, hy, math.radians(yaw)))
    goals = arrival_goals(target, len(dists))
    robots = []
    for d, ang in zip(dists, angles_deg):
        a = math.radians(ang)
        sx, sy = target[0] + d * math.cos(a), target[1] + d * math.sin(a)
        g = min(goals, key=lambda q: math.hypot(q[0] - target[0] - math.cos(a), q[1] - target[1] - math.sin(a)))
        goals.remove(g)
        robots.append(RobotSpec((sx, sy, math.atan2(target[1] - sy, target[0] - sx)), g))
    return World(boxes=boxes), robots


def phase2_tasks() -> list[tuple[World, list[RobotSpec]]]:
    """The phase-2 training tasks: :func:`phase2_task` and a second three-robot field (22, 35, 47 m)."""
    b = radial_task((15.0, 10.0), [22.0, 35.0, 47.0], [200, 265, 330],
                    [(0.5, 0.7, 2.0, 1.5, 0, 0), (0.4, -0.9, 2.5, 2.0, 10, 1), (0.7, 0.8, 2.0, 2.0, 0, 1),
                     (0.45, 0.9, 3.0, 1.5, 25, 2), (0.75, -1.0, 2.0, 2.0, 0, 2)])
    return [phase2_task(), b]


def arrival_goals(target: tuple[float, float], n: int, spacing: float = 2.0) -> list[tuple[float, float]]:
    """n goals on a circle around the target, ``spacing`` apart (so robots do not collide on arrival)."""
    if n == 1:
        return [target]
    rho = spacing / (2 * math.sin(math.pi / n))
    return [(target[0] + rho * math.cos(2 * math.pi * k / n + math.pi / 2),
             target[1] + rho * math.sin(2 * math.pi * k / n + math.pi / 2)) for k in range(n)]
