"""The vectorised training world of ``stack-train drl`` (numpy; replaces the paper's gazebo).

N independent environments step together, each with R unicycle robots (R = 1 in stage 1, 4 in
stage 2) among circles and boxes (walls are boxes, :meth:`stack.scenario.Obstacle.as_box`).

- Motion: the simulated differential drive of :mod:`stack.sim_bridge.world` (command -> wheel
  speeds limited in acceleration -> unicycle, exact arc), with the same default base.
- Lidar: analytic ray casts, the pybullet world's geometry: beams evenly from -fov/2 to +fov/2
  (both ends included), each ray from radius + 0.01 out to the range, robots and cylinders as
  circles, boxes as oriented rectangles; nothing hit reads the range. Gaussian noise, clipped.
- Collision and arrival: eq. (6)-(8): centre distance < 2 R_d to another robot, distance from
  the centre to an obstacle surface < R_d, within 0.5 m of the target (eq. 15).
- A robot that arrived or collided stops (it stays as an obstacle); an environment is done when
  its trained robot stops or after ``max_steps`` (a timeout, not a terminal state).
- ``follow`` scenes (ours, stage 3 ``--follow``): the targets move as the fleet's do. Robot 0 leads to
  its target at the speed of eq. (20) and the connectivity hold (the agent's own
  :meth:`stack.agents.decision.DecisionLayer.leader_speed`); every follower's target is its slot round
  the leader's position now (eq. 3, the slot = its start relative to the leader's), so a follower
  drives beside its neighbours for the whole way and arrives only once its leader has stopped.

Scenes (section V-A 1, Fig. 7): stage 1 one robot among random cylinders, boxes and walls, the
target a random distance away; stage 2 four robots in a formation-like layout (within 10 m of
each other), every target the robot's start translated by one common random vector; stage 3 (ours)
stretches of generated courses, 3-8 robots (:mod:`.course_scenes`; a scene's spare robots are parked
far away and never active).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stack.models.geometry import polar_array
from stack.models.kinematics import arc_step_array, body_rates, ramp, wheel_speeds
from stack.models.observation import neighbour_polar_array
from stack.policies.drl.observation import BEAMS, D_COM, N_SCANS, goal_features, neighbour_features
from stack.policies.drl.reward import GOAL_TOL, R_D, reward

FAR = 1.0e4  # padding obstacles live here


@dataclass
class WorldConfig:
    radius: float = R_D
    beams: int = BEAMS
    fov: float = math.pi
    scan_range: float = 5.0
    noise_std: float = 0.01  # the four-robot-obstacles scenario's lidar noise
    dt: float = 0.1  # Table I step size
    max_steps: int = 500  # Table I max-step
    track: float = 0.5  # stack.scenario.BaseConfig
    wheel_radius: float = 0.1
    wheel_accel: float = 30.0
    max_circles: int = 10
    max_boxes: int = 9
    robots: int = 4  # stage 2: robots per scene (the paper: four)
    max_walls: int = 2  # walls (2-10 m long thin boxes, across the way) per scene: 0..max_walls (0: the paper's
    # "randomly scattered" cuboids and cylinders only)
    time_penalty: float = 0.0  # per step, see stack.policies.drl.reward (0: the paper's reward)
    stall_steps: int = 0  # training only: a robot that has moved less than stall_move in this many steps ends its
    stall_move: float = 0.1  # episode with -stall_penalty, like a collision (0: off, the paper's episodes)
    stall_penalty: float = 1.0
    collision_penalty: float = 1.0  # eq. (16)'s -1 for a collision, as a positive penalty (stack.policies.drl.reward)
    follow: bool = False  # robot 0 leads, the others' targets are their slots round it (module docstring)
    leader_hold: tuple[float, float] | None = (0.8, 0.95)  # follow: DrlConfig.leader_hold's default


def scene_arrays(obstacles, max_circles: int | None = None, max_boxes: int | None = None):
    """Scenario obstacles -> (circles (Mc, 3) [x, y, r], boxes (Mb, 5) [cx, cy, hx, hy, yaw]), padded far away."""
    circ = [(o.x, o.y, o.radius) for o in obstacles if o.type == "cylinder"]
    box = [o.as_box() for o in obstacles if o.type != "cylinder"]
    mc = max(len(circ), max_circles or 0, 1)
    mb = max(len(box), max_boxes or 0, 1)
    c = np.tile(np.array([FAR, FAR, 0.0]), (mc, 1))
    b = np.tile(np.array([FAR, FAR, 0.0, 0.0, 0.0]), (mb, 1))
    if circ:
        c[: len(circ)] = circ
    if box:
        b[: len(box)] = box
    return c, b


def ray_cast(x, y, yaw, circles, boxes, beam_angles, r0: float, scan_range: float, dtype=np.float64) -> np.ndarray:
    """Ranges (..., B) of rays from (x, y) (shape (...)) at yaw + beam_angles, starting r0 from the centre.

    circles (..., Mc, 3) [x, y, r], boxes (..., Mb, 5) [cx, cy, hx, hy, yaw], broadcast against the
    ray origins' leading shape. A ray that starts inside a body reads r0. ``dtype``: the arithmetic's (the training
    world's float32 is within 0.1 mm of float64 at its scale and a quarter faster)."""
    if dtype != np.float64:
        x, y, yaw, circles, boxes, beam_angles = (np.asarray(v, dtype) for v in (x, y, yaw, circles, boxes, beam_angles))
    r0, inf, tiny = np.dtype(dtype).type(r0), np.dtype(dtype).type(np.inf), np.dtype(dtype).type(1e-12)
    a = yaw[..., None] + beam_angles  # (..., B)
    dx, dy = np.cos(a)[..., None], np.sin(a)[..., None]  # (..., B, 1)
    best = np.full(a.shape, scan_range, a.dtype)
    if circles.shape[-2] == 0 and boxes.shape[-2] == 0:
        return best
    circles = circles if circles.shape[-2] else np.zeros(circles.shape[:-2] + (1, 3))  # a point: hits nothing
    boxes = boxes if boxes.shape[-2] else np.zeros(boxes.shape[:-2] + (1, 5))  # hx = 0: hits nothing
    # circles: |o + t d - c| = r  ->  t = -b -+ sqrt(b^2 - (|o - c|^2 - r^2))
    ox = (x[..., None] - circles[..., 0])[..., None, :]  # (..., 1, M)
    oy = (y[..., None] - circles[..., 1])[..., None, :]
    b = ox * dx + oy * dy
    cc = ox * ox + oy * oy - (circles[..., 2] ** 2)[..., None, :]
    disc = b * b - cc
    sq = np.sqrt(np.maximum(disc, 0.0))
    t_in, t_out = -b - sq, -b + sq
    t = np.where(disc >= 0, np.where(t_in >= r0, t_in, np.where(t_out >= r0, r0, inf)), inf)
    best = np.minimum(best, t.min(axis=-1))
    # boxes: the slab method in each box's frame
    c, s = np.cos(boxes[..., 4]), np.sin(boxes[..., 4])
    px = (x[..., None] - boxes[..., 0])
    py = (y[..., None] - boxes[..., 1])
    lx, ly = (c * px + s * py)[..., None, :], (-s * px + c * py)[..., None, :]  # (..., 1, M)
    ca, sa = c[..., None, :], s[..., None, :]
    ldx = ca * dx + sa * dy  # (..., B, M)
    ldy = -sa * dx + ca * dy
    ldx = np.where(np.abs(ldx) < tiny, tiny, ldx)
    ldy = np.where(np.abs(ldy) < tiny, tiny, ldy)
    hx, hy = boxes[..., 2][..., None, :], boxes[..., 3][..., None, :]
    tx1, tx2 = (-hx - lx) / ldx, (hx - lx) / ldx
    ty1, ty2 = (-hy - ly) / ldy, (hy - ly) / ldy
    tmin = np.maximum(np.minimum(tx1, tx2), np.minimum(ty1, ty2))
    tmax = np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2))
    hit = (tmax >= tmin) & (tmax >= r0) & (hx > 0)
    t = np.where(hit, np.maximum(tmin, r0), inf)
    best = np.minimum(best, t.min(axis=-1))
    return best


def obstacle_distance(x, y, circles, boxes) -> np.ndarray:
    """Distance (...) from points to the nearest obstacle surface (0 inside), padded obstacles ignored."""
    d = np.hypot(x[..., None] - circles[..., 0], y[..., None] - circles[..., 1]) - circles[..., 2]
    c, s = np.cos(boxes[..., 4]), np.sin(boxes[..., 4])
    px, py = x[..., None] - boxes[..., 0], y[..., None] - boxes[..., 1]
    qx = np.abs(c * px + s * py) - boxes[..., 2]
    qy = np.abs(-s * px + c * py) - boxes[..., 3]
    db = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0)) + np.minimum(np.maximum(qx, qy), 0)
    return np.maximum(np.minimum(d.min(axis=-1), db.min(axis=-1)), 0.0)


def reachable(start, goal, circles, boxes, radius: float = R_D, cell: float = 0.1, margin: float = 0.05) -> bool:
    """Whether a disc of ``radius`` (+ ``margin``) can move from ``start`` to ``goal`` (the qlearn
    planner's 4-connected flood fill over a grid of free centre positions, 5 m around both)."""
    lo = np.minimum(start, goal) - 5.0
    hi = np.maximum(start, goal) + 5.0
    xs, ys = np.arange(lo[0], hi[0], cell), np.arange(lo[1], hi[1], cell)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    free = obstacle_distance(X, Y, circles, boxes) > radius + margin
    from stack.policies.qlearn import reachable as flood_fill

    cell_of = lambda p: (int((p[0] - lo[0]) / cell), int((p[1] - lo[1]) / cell))  # noqa: E731
    return flood_fill(~free, cell_of(start), cell_of(goal))


def _nearest(bodies: np.ndarray, key: np.ndarray, pad) -> np.ndarray:
    """bodies (..., M, k) -> (..., K, k): those with a finite key, nearest first, K the most any row has."""
    K = max(1, int(np.isfinite(key).sum(-1).max()))
    order = np.argsort(key, axis=-1)[..., :K]
    out = np.take_along_axis(bodies, order[..., None], axis=-2).copy()
    out[~np.isfinite(np.take_along_axis(key, order, axis=-1))] = pad
    return out


class DrlWorld:
    """N environments x R robots. ``observe()`` -> network inputs, ``step(actions)`` -> rewards."""

    def __init__(self, n_envs: int, stage: int = 1, *, seed: int = 0, cfg: WorldConfig | None = None,
                 scenes=None):
        self.cfg = cfg or WorldConfig()
        self.N, self.stage = n_envs, stage
        self.source = scenes  # rng -> a scene, instead of :meth:`_scene` (stage 3: .course_scenes.CourseScenes)
        self.R = 1 if stage == 1 else self.cfg.robots
        self.rng = np.random.default_rng(seed)
        N, R, c = self.N, self.R, self.cfg
        self.beam_angles = np.linspace(-c.fov / 2, c.fov / 2, c.beams)
        z = lambda: np.zeros((N, R))  # noqa: E731
        self.x, self.y, self.yaw, self.wl, self.wr, self.v, self.w = (z() for _ in range(7))
        self.gx, self.gy, self.d_prev = z(), z(), z()
        self.slot = np.zeros((N, R, 2))  # follow: each robot's place relative to the leader's (eq. 3's offset)
        self.a_prev = np.zeros((N, R, 2))
        self.active = np.ones((N, R), bool)
        self.present = np.ones((N, R), bool)  # robots in the scene (a scene's spare robots are parked at FAR)
        self.anchor = np.zeros((N, R, 3))  # x, y, step where each robot last moved stall_move (stall_steps)
        self.stalled = np.zeros((N, R), bool)  # this step ended a robot's episode by standing still
        self.held = np.zeros(N, bool)  # follow: the hold slowed the leader this step
        self.circles = np.zeros((N, c.max_circles, 3))
        self.boxes = np.zeros((N, c.max_boxes, 5))
        self.scans = np.zeros((N, R, N_SCANS, c.beams), np.float32)  # normalised, newest last
        self.t = np.zeros(N, int)
        self.trained = np.zeros(N, int)
        self.reset(np.ones(N, bool))

    # --- scenes ------------------------------------------------------------------------
    def _obstacles(self, rng, starts: np.ndarray, goals: np.ndarray, heading: float):
        """Random cylinders, boxes and walls around the starts and goals, none within 1 m of one."""
        c = self.cfg
        keep = np.vstack([starts, goals])
        lo, hi = keep.min(0) - 4.0, keep.max(0) + 4.0
        circles, boxes = [], []
        n_c, n_b, n_w = rng.integers(1, c.max_circles - 2), rng.integers(1, c.max_boxes - 3), rng.integers(0, c.max_walls + 1)
        on_path = rng.random() < 0.5  # one obstacle across a robot's straight path
        tries = 0
        while (len(circles) < n_c or len(boxes) < n_b + n_w) and tries < 200:
            tries += 1
            if on_path:
                k = rng.integers(len(starts))
                p = starts[k] + rng.uniform(0.3, 0.7) * (goals[k] - starts[k]) + rng.normal(0, 0.3, 2)
            else:
                p = rng.uniform(lo, hi)
            if len(circles) < n_c and (len(boxes) >= n_b + n_w or rng.random() < 0.5):
                cand = ("c", np.array([p[0], p[1], rng.uniform(0.25, 1.0)]))
            elif len(boxes) < n_b:
                cand = ("b", np.array([p[0], p[1], rng.uniform(0.2, 1.25), rng.uniform(0.2, 1.25), rng.uniform(-math.pi, math.pi)]))
            else:  # a wall: a long thin box
                cand = ("b", np.array([p[0], p[1], rng.uniform(2.0, 5.0), 0.1, heading + math.pi / 2 + rng.normal(0, 0.6)]))
            ci = np.array([cand[1]]) if cand[0] == "c" else np.zeros((0, 3)) + [FAR, FAR, 0]
            bi = np.array([cand[1]]) if cand[0] == "b" else np.zeros((0, 5)) + [FAR, FAR, 0, 0, 0]
            if obstacle_distance(keep[:, 0], keep[:, 1], np.vstack([ci, [[FAR, FAR, 0]]]), np.vstack([bi, [[FAR, FAR, 0, 0, 0]]])).min() < 2 * c.radius:
                continue
            on_path = False
            (circles if cand[0] == "c" else boxes).append(cand[1])
        cs = np.tile([FAR, FAR, 0.0], (c.max_circles, 1))
        bs = np.tile([FAR, FAR, 0.0, 0.0, 0.0], (c.max_boxes, 1))
        if circles:
            cs[: len(circles)] = circles
        if boxes:
            bs[: len(boxes)] = boxes
        return cs, bs

    def _scene(self, rng):
        """(starts (R, 2), yaws (R,), goals (R, 2), circles, boxes)."""
        if self.source is not None:
            return self.source(rng)
        if self.R == 1:
            heading = rng.uniform(-math.pi, math.pi)
            # mostly roughly toward the target (as in a formation), a quarter of the time any way
            yaw = heading + (rng.uniform(-math.pi, math.pi, 1) if rng.random() < 0.25 else rng.uniform(-math.pi / 2, math.pi / 2, 1))
            dist = rng.uniform(3.0, 10.0)
            starts = np.zeros((1, 2))
            goals = starts + dist * np.array([[math.cos(heading), math.sin(heading)]])
        else:
            heading = rng.uniform(-math.pi, math.pi)
            while True:  # leader at the origin, followers behind it (eq. 3 slots), 1.5 m apart at least
                L = rng.uniform(2.0, 5.0, self.R - 1)
                psi = heading + math.pi + rng.uniform(-1.4, 1.4, self.R - 1)
                starts = np.vstack([[0.0, 0.0], np.column_stack([L * np.cos(psi), L * np.sin(psi)])])
                d = np.hypot(*(starts[:, None] - starts[None]).transpose(2, 0, 1))
                if d[np.triu_indices(self.R, 1)].min() >= 1.5:
                    break
            yaw = heading + rng.normal(0.0, 0.4, self.R)
            shift = rng.uniform(5.0, 14.0) * np.array([math.cos(heading), math.sin(heading)])
            goals = starts + shift
        circles, boxes = self._obstacles(rng, starts, goals, heading)
        return starts, yaw, goals, circles, boxes

    def reset(self, mask: np.ndarray, scenes: list | None = None) -> None:
        """New scenes in the environments of ``mask`` (``scenes``: given ones, in order)."""
        idx = np.nonzero(mask)[0]
        for j, n in enumerate(idx):
            starts, yaw, goals, self.circles[n], self.boxes[n] = scenes[j] if scenes is not None else self._scene(self.rng)
            self.x[n], self.y[n], self.yaw[n] = starts[:, 0], starts[:, 1], yaw
            self.gx[n], self.gy[n] = goals[:, 0], goals[:, 1]
            self.slot[n] = starts - starts[0]
            self.present[n] = starts[:, 0] < FAR / 2  # parked robots are not in the scene
            live = np.flatnonzero(self.present[n])
            self.trained[n] = self.rng.integers(self.R) if len(live) == self.R else live[self.rng.integers(len(live))]
        for a in (self.wl, self.wr, self.v, self.w):
            a[idx] = 0.0
        self.a_prev[idx] = 0.0
        self.anchor[idx] = np.stack([self.x[idx], self.y[idx], np.zeros_like(self.x[idx])], -1)
        self.stalled[idx] = False
        self.active[idx] = self.present[idx]
        self.t[idx] = 0
        if self.cfg.follow:  # the followers' targets: their slots round the leader now (the scene's goals are
            self._move_slots()  # where they end up)
        self.d_prev[idx] = np.hypot(self.gx[idx] - self.x[idx], self.gy[idx] - self.y[idx])
        if len(idx):
            s = self._lidar(idx)
            self.scans[idx] = s[:, :, None, :]  # the first scan fills the history (the policy repeats the oldest too)

    # --- sensing -----------------------------------------------------------------------
    def _lidar(self, idx) -> np.ndarray:
        """Normalised scans (len(idx), R, B) of the environments ``idx``."""
        c = self.cfg
        x, y, yaw = self.x[idx], self.y[idx], self.yaw[idx]
        circles, boxes = self.circles[idx], self.boxes[idx]
        circles = circles[:, : max(1, int((circles[..., 2] > 0).sum(1).max()))]  # padding sits at the end: skip it
        boxes = boxes[:, : max(1, int((boxes[..., 2] > 0).sum(1).max()))]
        circ = np.broadcast_to(circles[:, None], (len(idx), self.R) + circles.shape[1:])
        if self.R > 1:  # the other robots are circles too (self left out: far away)
            rx = np.where(np.eye(self.R, dtype=bool)[None], FAR, x[:, None, :])
            ry = np.where(np.eye(self.R, dtype=bool)[None], FAR, y[:, None, :])
            circ = np.concatenate([circ, np.stack([rx, ry, np.full(rx.shape, c.radius)], -1)], axis=2)
        # exact culling: per robot only the bodies that come within range, nearest first
        reach = c.scan_range + 0.01
        dc = np.hypot(circ[..., 0] - x[..., None], circ[..., 1] - y[..., None]) - circ[..., 2]
        circ = _nearest(circ, np.where((dc <= reach) & (circ[..., 2] > 0), dc, np.inf), [FAR, FAR, 0.0])
        boxes = np.broadcast_to(boxes[:, None], (len(idx), self.R) + boxes.shape[1:])
        db = obstacle_distance(x[..., None], y[..., None], np.array([[FAR, FAR, 0.0]]), boxes[..., None, :])
        boxes = _nearest(boxes, np.where((db <= reach) & (boxes[..., 2] > 0), db, np.inf), [FAR, FAR, 0.0, 0.0, 0.0])
        r = ray_cast(x, y, yaw, circ, boxes, self.beam_angles, c.radius + 0.01, c.scan_range, np.float32)
        if c.noise_std > 0:
            r = r + self.rng.normal(0.0, c.noise_std, r.shape)
        return (np.clip(r, 0.0, c.scan_range) / c.scan_range).astype(np.float32)

    def _leader_speed(self, v: np.ndarray) -> np.ndarray:
        """Follow scenes: the leader's commanded speed (N,) after eq. (20) and the hold, d_rmax over the robots
        still driving (the agent's rule, :meth:`stack.agents.decision.DecisionLayer.leader_speed`; a robot that
        stopped holds no one, as the fleet's hold gives up on a robot that does not come). Sets ``held``: where
        the hold, not the network, slowed the leader."""
        from stack.agents.decision import DecisionLayer

        d = np.hypot(self.x - self.x[:, :1], self.y - self.y[:, :1])
        d_rmax = np.where(self.active, d, 0.0).max(axis=1)
        out = np.array([DecisionLayer.leader_speed(float(vi), float(di), hold=self.cfg.leader_hold, d_com=D_COM)
                        for vi, di in zip(v, d_rmax)])
        self.held = out < v - 1e-9
        return out

    def _move_slots(self) -> None:
        """Follow scenes: every follower's target is its slot round the leader where it is now (eq. 3)."""
        f = self.present.copy()
        f[:, 0] = False
        self.gx = np.where(f, self.x[:, :1] + self.slot[..., 0], self.gx)
        self.gy = np.where(f, self.y[:, :1] + self.slot[..., 1], self.gy)

    def _robot_distances(self) -> np.ndarray:
        """(N, R, R) centre distances, inf on the diagonal."""
        d = np.hypot(self.x[:, :, None] - self.x[:, None], self.y[:, :, None] - self.y[:, None])
        d[:, np.arange(self.R), np.arange(self.R)] = np.inf
        return d

    def observe(self) -> dict[str, np.ndarray]:
        """Network inputs for every robot: scans (N, R, 3, B), gv (N, R, 4), nb (N, R, R-1, 2), n_nb (N, R)."""
        d_g, alpha = polar_array(self.x, self.y, self.yaw, self.gx, self.gy)  # as the agent's decision layer
        gv = goal_features(d_g, alpha, self.v, self.w)
        N, R = self.N, self.R
        nb = np.zeros((N, R, max(R - 1, 0), 2), np.float32)
        n_nb = np.zeros((N, R), np.int64)
        if R > 1:
            polar, n_nb = neighbour_polar_array(self.x, self.y, self.yaw, D_COM)
            nb = neighbour_features(polar).reshape(N, R, R - 1, 2)
        return {"scans": self.scans, "gv": gv, "nb": nb, "n_nb": n_nb}

    # --- dynamics ----------------------------------------------------------------------
    def step(self, actions: np.ndarray, table: np.ndarray):
        """Apply action indices (N, R) (stopped robots get zero). Returns per robot (N, R):
        reward (eq. 14), arrived, collided, and per environment (N,): done, timeout."""
        c = self.cfg
        a = table[actions].astype(float)  # (N, R, 2)
        a[~self.active] = 0.0
        leading = self.active[:, 0].copy()
        if c.follow:
            a[:, 0, 0] = self._leader_speed(a[:, 0, 0])
        v_c, w_c = a[..., 0], a[..., 1]
        wl_t, wr_t = wheel_speeds(v_c, w_c, c.track, c.wheel_radius)  # the pybullet world's drive (stack.models)
        dmax = c.wheel_accel * c.dt
        self.wl, self.wr = ramp(self.wl, wl_t, dmax), ramp(self.wr, wr_t, dmax)
        self.v, self.w = body_rates(self.wl, self.wr, c.track, c.wheel_radius)
        self.x, self.y, self.yaw = arc_step_array(self.x, self.y, self.yaw, self.v, self.w, c.dt)
        self.t += 1
        can_arrive = True
        if c.follow:
            self._move_slots()
            can_arrive = np.ones((self.N, self.R), bool)
            can_arrive[:, 1:] = ~leading[:, None]  # a follower's slot stands still once its leader has stopped
        d_now = np.hypot(self.gx - self.x, self.gy - self.y)
        d_rob = self._robot_distances().min(axis=2) if self.R > 1 else np.full((self.N, 1), np.inf)
        d_obs = obstacle_distance(self.x, self.y, self.circles[:, None], self.boxes[:, None])
        r, arrived, collided = reward(self.d_prev, d_now, d_rob, d_obs, self.a_prev, a, c.radius, c.time_penalty,
                                      can_arrive, c.collision_penalty)
        r = np.where(self.active, r, 0.0)
        arrived &= self.active
        collided &= self.active & ~arrived
        self.active &= ~(arrived | collided)
        self.stalled[:] = False
        if c.stall_steps:  # training only: standing (or turning on the spot) for stall_steps ends the episode
            moved = np.hypot(self.x - self.anchor[..., 0], self.y - self.anchor[..., 1]) > c.stall_move
            moved |= d_now <= GOAL_TOL  # waiting on its (follow: moving) target is not standing still
            if c.follow:
                moved[:, 0] |= self.held  # nor is a leader the hold slows
            self.anchor[moved] = np.stack([self.x[moved], self.y[moved], np.broadcast_to(self.t[:, None], moved.shape)[moved]], -1)
            self.stalled = self.active & (self.t[:, None] - self.anchor[..., 2] >= c.stall_steps)
            r = np.where(self.stalled, r - c.stall_penalty, r)
            self.active &= ~self.stalled
        self.d_prev, self.a_prev = d_now, a
        self.scans = np.concatenate([self.scans[:, :, 1:], self._lidar(np.arange(self.N))[:, :, None]], axis=2)
        tr = self.trained
        done_tr = ~self.active[np.arange(self.N), tr]
        timeout = (self.t >= c.max_steps) & ~done_tr
        return r, arrived, collided, done_tr | timeout, timeout


def held_out_scenes(n: int, stage: int = 1, seed: int = 20260 + 1, max_walls: int = 2, robots: int = 4) -> list:
    """A fixed set of scenes (the held-out evaluation set; training seeds never reach this one's stream).
    ``max_walls`` 0: the paper's scenes (cuboids and cylinders randomly scattered, section V-A)."""
    w = DrlWorld.__new__(DrlWorld)
    w.cfg, w.R, w.source = WorldConfig(max_walls=max_walls, robots=robots), 1 if stage == 1 else robots, None
    rng = np.random.default_rng([seed, stage])
    return [w._scene(rng) for _ in range(n)]
