"""The pybullet world: robot bodies, obstacles, 2D lidar by ``rayTestBatch``, wheel odometry, IMU.

Robots and cylinder obstacles collide as spheres centred in the lidar's scan plane: their
cross-section there is exactly the 2D disc, and Bullet casts rays against spheres about
seven times faster than against cylinders (what is drawn in the GUI is still a cylinder).

Robots are kinematic differential-drive bodies: a command (v, w) becomes left/right wheel
speeds, each limited in acceleration, and the body moves by the unicycle model (exact arc)
from the resulting wheel speeds (:mod:`stack.models.kinematics`, the training worlds' and the EKF's model). pybullet holds the geometry: every lidar ray is a real
``rayTestBatch`` against the obstacles and the other robots' bodies. Collisions are not
resolved physically; they are measured (centre distances, INTERFACES.md section 3).
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p

from ..models.kinematics import arc_step, arc_step_array, body_rates, ramp, wheel_speeds

ROBOT_HEIGHT = 0.4
OBSTACLE_HEIGHT = 1.0
LIDAR_Z = 0.2
CULL_MARGIN = 0.05  # [m] added around every body when culling beams
IN_SITE, VIRTUAL = 1, 2
"""Collision groups, with real robots in the fleet: bodies that stand in the real site (real robots, obstacles not
marked virtual), which a real lidar sees for itself; and bodies only the world has (simulated robots, virtual
obstacles), which a virtual scan casts against (``virtual_scan``). Simulated lidars see both."""


class World:
    def __init__(self, scenario, *, gui: bool = False, seed: int | None = None):
        self.sc = scenario
        self.cid = p.connect(p.GUI if gui else p.DIRECT)
        p.setGravity(0, 0, 0, physicsClientId=self.cid)
        self.seed = scenario.seed if seed is None else seed
        self.rng = np.random.default_rng(self.seed)
        self._cast_rngs: dict[int, np.random.Generator] = {}  # lidar_at's noise, per robot index
        self.ids = [r.id for r in scenario.robots]
        self.index = {rid: i for i, rid in enumerate(self.ids)}
        n = len(self.ids)
        self.x = np.array([r.pose[0] for r in scenario.robots], float)
        self.y = np.array([r.pose[1] for r in scenario.robots], float)
        self.yaw = np.array([r.pose[2] for r in scenario.robots], float)
        self.wl = np.zeros(n)  # wheel angular speeds [rad/s]
        self.wr = np.zeros(n)
        self.v = np.zeros(n)
        self.w = np.zeros(n)
        self.radii = np.array([r.radius for r in scenario.robots], float)
        self.track = np.array([r.base.track for r in scenario.robots], float)
        self.wheel_radius = np.array([r.base.wheel_radius for r in scenario.robots], float)
        self.wheel_accel = np.array([r.base.wheel_accel for r in scenario.robots], float)
        # each base's dead-reckoned pose from its own (noisy) encoder speeds, as a real base's odometry reports it
        self.odo_pose = np.column_stack([self.x, self.y, self.yaw]).astype(float)
        self.obstacle_bodies = [self._add_obstacle(o) for o in scenario.obstacles]
        self.robot_bodies = [self._add_robot(r) for r in scenario.robots]
        self.mixed = any(r.embodiment == "real" for r in scenario.robots)
        if self.mixed:
            for b, o in zip(self.obstacle_bodies, scenario.obstacles):
                self._group(b, VIRTUAL if o.virtual else IN_SITE)
            for b, r in zip(self.robot_bodies, scenario.robots):
                self._group(b, IN_SITE if r.embodiment == "real" else VIRTUAL)
        self._sync_bodies()
        self._ray_setup()
        aabbs = [p.getAABB(b, physicsClientId=self.cid) for b in self.obstacle_bodies]
        self.obstacle_aabbs = np.array([[a[0][:2], a[1][:2]] for a in aabbs]).reshape(-1, 2, 2)
        self.cull = True  # cast only the beams that can hit something (exact; see _beam_mask)
        self.rays_cast = 0

    # --- construction ------------------------------------------------------------------
    def _add_obstacle(self, o) -> int:
        c = self.cid
        if o.type == "cylinder":
            # collision: a sphere centred in the scan plane (same circle there, and 7x cheaper rays than a cylinder)
            shape = p.createCollisionShape(p.GEOM_SPHERE, radius=o.radius, physicsClientId=c)
            vis = p.createVisualShape(p.GEOM_CYLINDER, radius=o.radius, length=OBSTACLE_HEIGHT, rgbaColor=[0.8, 0.2, 0.2, 1],
                                      visualFramePosition=[0, 0, OBSTACLE_HEIGHT / 2 - LIDAR_Z], physicsClientId=c)
            return p.createMultiBody(0, shape, vis, [o.x, o.y, LIDAR_Z], physicsClientId=c)
        cx, cy, hx, hy, yaw = o.as_box()
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[hx, hy, OBSTACLE_HEIGHT / 2], physicsClientId=c)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=[hx, hy, OBSTACLE_HEIGHT / 2], rgbaColor=[0.8, 0.3, 0.2, 1], physicsClientId=c)
        return p.createMultiBody(0, shape, vis, [cx, cy, OBSTACLE_HEIGHT / 2], p.getQuaternionFromEuler([0, 0, yaw]), physicsClientId=c)

    def _add_robot(self, r, radius: float | None = None) -> int:
        c, radius = self.cid, r.radius if radius is None else radius
        shape = p.createCollisionShape(p.GEOM_SPHERE, radius=radius, physicsClientId=c)  # see _add_obstacle
        vis = p.createVisualShape(p.GEOM_CYLINDER, radius=radius, length=ROBOT_HEIGHT, rgbaColor=[0.2, 0.4, 0.9, 1],
                                  visualFramePosition=[0, 0, ROBOT_HEIGHT / 2 - LIDAR_Z], physicsClientId=c)
        return p.createMultiBody(0, shape, vis, [r.pose[0], r.pose[1], LIDAR_Z], physicsClientId=c)

    def _group(self, body: int, group: int) -> None:
        p.setCollisionFilterGroupMask(body, -1, group, IN_SITE | VIRTUAL, physicsClientId=self.cid)

    def set_radius(self, rid: int, radius: float) -> None:
        """Robot ``rid``'s body as a disc of ``radius`` (a real robot whose pose went stale grows by what it could
        have driven since: the simulated robots' lidars and guards give it that berth)."""
        i = self.index[rid]
        if radius == self.radii[i]:
            return
        r = self.sc.robots[i]
        p.removeBody(self.robot_bodies[i], physicsClientId=self.cid)
        self.robot_bodies[i] = self._add_robot(r, radius)
        if self.mixed:
            self._group(self.robot_bodies[i], IN_SITE if r.embodiment == "real" else VIRTUAL)
        self.radii[i] = radius
        self._sync_body(i)

    def place(self, rid: int, x: float, y: float, yaw: float, v: float, w: float) -> None:
        """A robot the world does not move (a real one) is where its pose source says, at that speed."""
        i = self.index[rid]
        self.x[i], self.y[i], self.yaw[i], self.v[i], self.w[i] = x, y, yaw, v, w
        self.odo_pose[i] = (x, y, yaw)
        self.wl[i] = self.wr[i] = 0.0
        self._sync_body(i)

    def _ray_setup(self) -> None:
        """Per robot: beam angles (robot frame), start offset (outside its own body) and range."""
        self.beam_angles = []
        self.ray_offsets = []
        for r in self.sc.robots:
            lid = r.lidar
            if lid.beams == 1:
                ang = np.zeros(1)
            else:
                ang = np.linspace(-lid.fov / 2, lid.fov / 2, lid.beams)
            self.beam_angles.append(ang)
            self.ray_offsets.append(r.radius + 0.01)

    def _sync_bodies(self) -> None:
        for i in range(len(self.robot_bodies)):
            self._sync_body(i)

    def _sync_body(self, i: int) -> None:
        p.resetBasePositionAndOrientation(self.robot_bodies[i], [self.x[i], self.y[i], LIDAR_Z],
                                          p.getQuaternionFromEuler([0, 0, self.yaw[i]]), physicsClientId=self.cid)

    # --- dynamics ----------------------------------------------------------------------
    def step(self, commands: dict[int, tuple[float, float]], dt: float, exact: frozenset[int] | set[int] = frozenset()) -> None:
        """Advance by dt: commands -> wheel speeds (acceleration-limited) -> unicycle motion.

        Robots in ``exact`` move with their (v, w) as given: a hosted device (an ODrive pair, a
        rover's autopilot) already ramped its actuators, and the body follows them."""
        v_c = np.array([commands.get(rid, (0.0, 0.0))[0] for rid in self.ids], float)
        w_c = np.array([commands.get(rid, (0.0, 0.0))[1] for rid in self.ids], float)
        wl_t, wr_t = wheel_speeds(v_c, w_c, self.track, self.wheel_radius)  # inverse kinematics
        dmax = np.where([rid in exact for rid in self.ids], math.inf, self.wheel_accel * dt)
        self.wl[:], self.wr[:] = ramp(self.wl, wl_t, dmax), ramp(self.wr, wr_t, dmax)
        self.v[:], self.w[:] = body_rates(self.wl, self.wr, self.track, self.wheel_radius)
        self.x[:], self.y[:], self.yaw[:] = arc_step_array(self.x, self.y, self.yaw, self.v, self.w, dt)
        self._sync_bodies()

    # --- sensors -----------------------------------------------------------------------
    def _beam_masks(self, idx: list[int], poses: np.ndarray | None = None,
                    angles: list[np.ndarray] | None = None) -> list[np.ndarray]:
        """For each robot index in ``idx`` (standing at ``poses[j]`` = (x, y, yaw), default where it is, with beam
        angles ``angles[j]``, default its lidar's): the beams that can hit anything, those inside the angular span
        of a body within range. One numpy pass over every (robot, nearby body) pair of the part.

        Exact culling, not an approximation: a beam outside every nearby body's span cannot hit,
        so it is not cast and reads max range. Static obstacles are bounded by their pybullet AABBs,
        robots by their circles; both grown by CULL_MARGIN (Bullet's collision margin). Rays that start inside
        or at a body (another robot's disc, a box's AABB) are all cast.
        """
        I = np.asarray(idx, int)
        pose = np.column_stack([self.x[I], self.y[I], self.yaw[I]]) if poses is None else np.asarray(poses, float)
        ang = [self.beam_angles[i] for i in idx] if angles is None else angles
        x, y, yaw = pose[:, 0:1], pose[:, 1:2], pose[:, 2]
        rng = np.array([self.sc.robots[i].lidar.range for i in idx])[:, None]
        r0 = np.array([self.ray_offsets[i] for i in idx])[:, None]
        # other robots: discs
        dx, dy = self.x[None, :] - x, self.y[None, :] - y
        rj = np.broadcast_to(self.radii[None, :] + CULL_MARGIN, dx.shape)
        d = np.hypot(dx, dy)
        near = d - rj <= rng
        near[np.arange(len(I)), I] = False  # not itself
        cast_all = (near & (d - rj <= r0)).any(1)
        rows, cols = np.nonzero(near)
        centres = [np.arctan2(dy[rows, cols], dx[rows, cols])]
        halves = [np.arcsin(np.minimum(1.0, rj[rows, cols] / d[rows, cols]))]
        pair_rows = [rows]
        # obstacles: axis-aligned boxes from pybullet's AABBs
        if len(self.obstacle_aabbs):
            lo, hi = self.obstacle_aabbs[:, 0], self.obstacle_aabbs[:, 1]
            ddx = np.maximum(np.maximum(lo[None, :, 0] - x, 0.0), x - hi[None, :, 0])
            ddy = np.maximum(np.maximum(lo[None, :, 1] - y, 0.0), y - hi[None, :, 1])
            dd = np.hypot(ddx, ddy)
            near_o = dd <= rng
            cast_all |= (near_o & (dd <= r0 + CULL_MARGIN)).any(1)
            rows, cols = np.nonzero(near_o)
            px, py = x[rows, 0][:, None], y[rows, 0][:, None]
            l, h = lo[cols], hi[cols]
            cx = np.stack([l[:, 0], h[:, 0], l[:, 0], h[:, 0]], 1) - px
            cy = np.stack([l[:, 1], l[:, 1], h[:, 1], h[:, 1]], 1) - py
            corners = np.arctan2(cy, cx)  # (pairs, 4)
            mid = np.arctan2(np.sin(corners).sum(1), np.cos(corners).sum(1))
            offs = (corners - mid[:, None] + np.pi) % (2 * np.pi) - np.pi
            with np.errstate(divide="ignore"):  # a robot inside a box's AABB (dd 0) casts all its beams anyway
                pad = np.arcsin(np.minimum(1.0, CULL_MARGIN / dd[rows, cols]))
            lo_a, hi_a = mid + offs.min(1) - pad, mid + offs.max(1) + pad
            centres.append((lo_a + hi_a) / 2)
            halves.append((hi_a - lo_a) / 2)
            pair_rows.append(rows)
        rows = np.concatenate(pair_rows)
        c = np.concatenate(centres) - yaw[rows]  # to each robot's frame
        h = np.concatenate(halves)
        return [np.ones(ang[j].size, bool) if cast_all[j] else self._within(ang[j], c[rows == j], h[rows == j])
                for j in range(len(I))]

    @staticmethod
    def _within(ang: np.ndarray, c: np.ndarray, h: np.ndarray) -> np.ndarray:
        """The beams at ``ang`` within any span (centre ``c``, half-width ``h``)."""
        if c.size == 0:
            return np.zeros(ang.size, bool)
        diff = (ang[None, :] - c[:, None] + np.pi) % (2 * np.pi) - np.pi
        return (np.abs(diff) <= h[:, None]).any(axis=0)

    def _rays(self, i: int, x: float, y: float, yaw: float, ang: np.ndarray,
              m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Robot i's rays from (x, y, yaw) at beam angles ``ang``, of the beams in ``m``: (m, froms, tos)."""
        lid = self.sc.robots[i].lidar
        a = yaw + ang[m]
        c, s = np.cos(a), np.sin(a)
        r0 = self.ray_offsets[i]
        z = np.full(a.size, LIDAR_Z)
        froms = np.column_stack([x + r0 * c, y + r0 * s, z])
        return m, froms, np.column_stack([x + lid.range * c, y + lid.range * s, z])

    def _cast(self, froms: list[np.ndarray], tos: list[np.ndarray], mask: int = -1) -> np.ndarray:
        """Hit fractions of the rays (1: no hit), by ``rayTestBatch`` in batches; ``mask``: the collision groups
        the rays hit (default all)."""
        F = np.concatenate(froms) if froms else np.zeros((0, 3))
        T = np.concatenate(tos) if tos else np.zeros((0, 3))
        fracs = np.ones(len(F))
        batch = p.MAX_RAY_INTERSECTION_BATCH_SIZE - 1
        for s0 in range(0, len(F), batch):
            # numpy arrays as they are (pybullet reads them directly: a third cheaper than lists of floats here)
            res = p.rayTestBatch(F[s0:s0 + batch], T[s0:s0 + batch], numThreads=1, collisionFilterMask=mask,
                                 physicsClientId=self.cid)
            fracs[s0:s0 + len(res)] = [h[2] if h[0] >= 0 else 1.0 for h in res]
        self.rays_cast += len(F)
        return fracs

    def _ranges(self, i: int, m: np.ndarray, fracs: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
        """Robot i's ranges from the hit fractions of its cast beams (``m``): ``noise`` added, clipped to [0, range]."""
        lid = self.sc.robots[i].lidar
        r0 = self.ray_offsets[i]
        f = np.ones(m.size)
        f[m] = fracs
        ranges = np.where(f >= 1.0, lid.range, r0 + f * (lid.range - r0))
        if noise is not None:
            ranges = ranges + noise
        return np.clip(ranges, 0.0, lid.range)

    def _noise(self, i: int, rng: np.random.Generator, beams: int | None = None) -> np.ndarray | None:
        """Robot i's range noise for one scan of ``beams`` beams (default its lidar's; None: a noiseless lidar). It
        depends on no ray, so it can be drawn before the cast."""
        lid = self.sc.robots[i].lidar
        n = self.beam_angles[i].size if beams is None else beams
        return rng.normal(0.0, lid.noise_std, n) if lid.noise_std > 0 else None

    def lidar_noise(self, which: list[int]) -> dict[int, np.ndarray | None]:
        """The range noise of these robots' next scans from the world's generator, in this order: what ``lidar(which)``
        draws itself, drawn ahead so that the world can cast its robots in parts (``lidar(part, noise=...)``) and
        hand each part on at once with the same numbers."""
        return {rid: self._noise(self.index[rid], self.rng) for rid in which}

    def lidar(self, which: list[int] | None = None, noise: dict[int, np.ndarray | None] | None = None) -> dict[int, np.ndarray]:
        """Ranges per robot from one ``rayTestBatch`` (noise added, clipped to [0, range]); ``noise``: drawn ahead
        (``lidar_noise``), else drawn here."""
        which = list(which if which is not None else self.ids)
        noise = noise if noise is not None else self.lidar_noise(which)
        idx = [self.index[r] for r in which]
        masks = self._beam_masks(idx) if self.cull else [np.ones(self.beam_angles[i].size, bool) for i in idx]
        rays = [self._rays(i, self.x[i], self.y[i], self.yaw[i], self.beam_angles[i], m) for i, m in zip(idx, masks)]
        fracs = self._cast([f for _, f, _ in rays], [t for _, _, t in rays])
        out, pos = {}, 0
        for rid, i, (m, _, _) in zip(which, idx, rays):
            n = int(m.sum())
            out[rid] = self._ranges(i, m, fracs[pos:pos + n], noise[rid])
            pos += n
        return out

    def lidar_at(self, rid: int, pose: tuple[float, float, float], angles) -> np.ndarray:
        """Robot ``rid``'s lidar cast as if it stood at ``pose`` (x, y, yaw; world frame) with beam ``angles``
        (robot frame): the rays, culling, range and noise of ``lidar()``, the other bodies where they are now.

        For a simulated device that scans at its own times between world steps (its ``ray_caster``). The
        robot's body moves to ``pose`` for the cast and back after it; the noise comes from the robot's
        own generator (seeded by the world's seed and the robot id), so extra scans leave the world's
        own scans and odometry as they were: deterministic, whoever casts how often.
        """
        i = self.index[rid]
        x, y, yaw = (float(v) for v in pose)
        ang = np.asarray(angles, float).reshape(-1)
        body = self.robot_bodies[i]
        moved = (x, y, yaw) != (self.x[i], self.y[i], self.yaw[i])
        if moved:
            p.resetBasePositionAndOrientation(body, [x, y, LIDAR_Z], p.getQuaternionFromEuler([0, 0, yaw]),
                                              physicsClientId=self.cid)
        try:
            m = self._beam_masks([i], np.array([[x, y, yaw]]), [ang])[0] if self.cull else np.ones(ang.size, bool)
            m, froms, tos = self._rays(i, x, y, yaw, ang, m)
            fracs = self._cast([froms], [tos])
        finally:
            if moved:
                self._sync_body(i)
        return self._ranges(i, m, fracs, self._noise(i, self._cast_rng(i), ang.size))

    def virtual_scan(self, rid: int) -> np.ndarray:
        """Real robot ``rid``'s lidar beams (its configured layout, from its body's centre, where its pose source
        put it) cast against the virtual bodies only, without noise: what its real lidar would see of the robots and
        obstacles that exist only here. No hit reads the lidar's range."""
        i = self.index[rid]
        ang = self.beam_angles[i]
        m, froms, tos = self._rays(i, self.x[i], self.y[i], self.yaw[i], ang, np.ones(ang.size, bool))
        return self._ranges(i, m, self._cast([froms], [tos], mask=VIRTUAL), None)

    def _cast_rng(self, i: int) -> np.random.Generator:
        if i not in self._cast_rngs:
            self._cast_rngs[i] = np.random.default_rng([self.seed, self.ids[i], 0x11DA])
        return self._cast_rngs[i]

    def odometry(self, rid: int, dt: float) -> tuple[float, float, tuple[float, float, float]]:
        """Encoder speeds (v, w) with the robot's odometry noise, and the base's dead-reckoned pose
        before them (x, y, yaw in the world frame; it then integrates them over ``dt``)."""
        i = self.index[rid]
        v_std, w_std = self.sc.robots[i].odom_noise
        v = float(self.v[i] + (self.rng.normal(0, v_std) if v_std > 0 else 0.0))
        w = float(self.w[i] + (self.rng.normal(0, w_std) if w_std > 0 else 0.0))
        x, y, yaw = (float(a) for a in self.odo_pose[i])
        self.odo_pose[i] = arc_step(x, y, yaw, v, w, dt)
        return v, w, (x, y, yaw)

    def gyro(self, rid: int) -> float:
        i = self.index[rid]
        std = self.sc.robots[i].imu_noise
        return float(self.w[i] + (self.rng.normal(0, std) if std > 0 else 0.0))

    def position_fix(self, rid: int, std: float) -> tuple[float, float]:
        """A noisy absolute position (GNSS / motion-capture stand-in)."""
        i = self.index[rid]
        return float(self.x[i] + self.rng.normal(0, std)), float(self.y[i] + self.rng.normal(0, std))

    def close(self) -> None:
        try:
            p.disconnect(physicsClientId=self.cid)
        except p.error:
            pass
