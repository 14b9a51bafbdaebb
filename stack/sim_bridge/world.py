"""The pybullet world: robot bodies, obstacles, 2D lidar by ``rayTestBatch``, wheel odometry, IMU.

Robots are kinematic differential-drive bodies: a command (v, w) becomes left/right wheel
speeds, each limited in acceleration, and the body moves by the unicycle model (exact arc)
from the resulting wheel speeds. pybullet holds the geometry: every lidar ray is a real
``rayTestBatch`` against the obstacles and the other robots' bodies. Collisions are not
resolved physically; they are measured (centre distances, INTERFACES.md section 3).
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p

ROBOT_HEIGHT = 0.4
OBSTACLE_HEIGHT = 1.0
LIDAR_Z = 0.2


class World:
    def __init__(self, scenario, *, gui: bool = False, seed: int | None = None):
        self.sc = scenario
        self.cid = p.connect(p.GUI if gui else p.DIRECT)
        p.setGravity(0, 0, 0, physicsClientId=self.cid)
        self.rng = np.random.default_rng(scenario.seed if seed is None else seed)
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
        self.obstacle_bodies = [self._add_obstacle(o) for o in scenario.obstacles]
        self.robot_bodies = [self._add_robot(r) for r in scenario.robots]
        self._sync_bodies()
        self._ray_setup()

    # --- construction ------------------------------------------------------------------
    def _add_obstacle(self, o) -> int:
        c = self.cid
        if o.type == "cylinder":
            shape = p.createCollisionShape(p.GEOM_CYLINDER, radius=o.radius, height=OBSTACLE_HEIGHT, physicsClientId=c)
            vis = p.createVisualShape(p.GEOM_CYLINDER, radius=o.radius, length=OBSTACLE_HEIGHT, rgbaColor=[0.8, 0.2, 0.2, 1], physicsClientId=c)
            return p.createMultiBody(0, shape, vis, [o.x, o.y, OBSTACLE_HEIGHT / 2], physicsClientId=c)
        cx, cy, hx, hy, yaw = o.as_box()
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[hx, hy, OBSTACLE_HEIGHT / 2], physicsClientId=c)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=[hx, hy, OBSTACLE_HEIGHT / 2], rgbaColor=[0.8, 0.3, 0.2, 1], physicsClientId=c)
        return p.createMultiBody(0, shape, vis, [cx, cy, OBSTACLE_HEIGHT / 2], p.getQuaternionFromEuler([0, 0, yaw]), physicsClientId=c)

    def _add_robot(self, r) -> int:
        c = self.cid
        shape = p.createCollisionShape(p.GEOM_CYLINDER, radius=r.radius, height=ROBOT_HEIGHT, physicsClientId=c)
        vis = p.createVisualShape(p.GEOM_CYLINDER, radius=r.radius, length=ROBOT_HEIGHT, rgbaColor=[0.2, 0.4, 0.9, 1], physicsClientId=c)
        return p.createMultiBody(0, shape, vis, [r.pose[0], r.pose[1], ROBOT_HEIGHT / 2], physicsClientId=c)

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
        for i, b in enumerate(self.robot_bodies):
            p.resetBasePositionAndOrientation(b, [self.x[i], self.y[i], ROBOT_HEIGHT / 2],
                                              p.getQuaternionFromEuler([0, 0, self.yaw[i]]), physicsClientId=self.cid)

    # --- dynamics ----------------------------------------------------------------------
    def step(self, commands: dict[int, tuple[float, float]], dt: float) -> None:
        """Advance by dt: commands -> wheel speeds (acceleration-limited) -> unicycle motion."""
        for rid, i in self.index.items():
            r = self.sc.robots[i]
            b = r.base
            v_c, w_c = commands.get(rid, (0.0, 0.0))
            # differential drive inverse kinematics: wheel angular speeds for (v, w)
            wl_t = (v_c - w_c * b.track / 2) / b.wheel_radius
            wr_t = (v_c + w_c * b.track / 2) / b.wheel_radius
            dmax = b.wheel_accel * dt
            self.wl[i] += max(-dmax, min(dmax, wl_t - self.wl[i]))
            self.wr[i] += max(-dmax, min(dmax, wr_t - self.wr[i]))
            v = b.wheel_radius * (self.wr[i] + self.wl[i]) / 2
            w = b.wheel_radius * (self.wr[i] - self.wl[i]) / b.track
            th = self.yaw[i]
            if abs(w) < 1e-9:
                self.x[i] += v * dt * math.cos(th)
                self.y[i] += v * dt * math.sin(th)
            else:
                self.x[i] += v / w * (math.sin(th + w * dt) - math.sin(th))
                self.y[i] -= v / w * (math.cos(th + w * dt) - math.cos(th))
            self.yaw[i] = math.atan2(math.sin(th + w * dt), math.cos(th + w * dt))
            self.v[i], self.w[i] = v, w
        self._sync_bodies()

    # --- sensors -----------------------------------------------------------------------
    def lidar(self, which: list[int] | None = None) -> dict[int, np.ndarray]:
        """Ranges per robot from one ``rayTestBatch`` (noise added, clipped to [0, range])."""
        idx = [self.index[r] for r in (which if which is not None else self.ids)]
        froms, tos, spans = [], [], []
        for i in idx:
            lid = self.sc.robots[i].lidar
            a = self.yaw[i] + self.beam_angles[i]
            c, s = np.cos(a), np.sin(a)
            r0 = self.ray_offsets[i]
            f = np.column_stack([self.x[i] + r0 * c, self.y[i] + r0 * s, np.full(a.size, LIDAR_Z)])
            t = np.column_stack([self.x[i] + lid.range * c, self.y[i] + lid.range * s, np.full(a.size, LIDAR_Z)])
            froms.append(f)
            tos.append(t)
            spans.append(a.size)
        if not froms:
            return {}
        F = np.concatenate(froms)
        T = np.concatenate(tos)
        fracs = np.empty(len(F))
        batch = p.MAX_RAY_INTERSECTION_BATCH_SIZE - 1
        for s0 in range(0, len(F), batch):
            res = p.rayTestBatch(F[s0:s0 + batch].tolist(), T[s0:s0 + batch].tolist(), physicsClientId=self.cid)
            fracs[s0:s0 + len(res)] = [h[2] if h[0] >= 0 else 1.0 for h in res]
        out = {}
        pos = 0
        for i, n in zip(idx, spans):
            lid = self.sc.robots[i].lidar
            r0 = self.ray_offsets[i]
            ranges = r0 + fracs[pos:pos + n] * (lid.range - r0)
            ranges[fracs[pos:pos + n] >= 1.0] = lid.range
            if lid.noise_std > 0:
                ranges = ranges + self.rng.normal(0.0, lid.noise_std, n)
            out[self.ids[i]] = np.clip(ranges, 0.0, lid.range)
            pos += n
        return out

    def odometry(self, rid: int) -> tuple[float, float]:
        """Encoder speeds (v, w) with the robot's odometry noise."""
        i = self.index[rid]
        v_std, w_std = self.sc.robots[i].odom_noise
        v = self.v[i] + (self.rng.normal(0, v_std) if v_std > 0 else 0.0)
        w = self.w[i] + (self.rng.normal(0, w_std) if w_std > 0 else 0.0)
        return float(v), float(w)

    def gyro(self, rid: int) -> float:
        i = self.index[rid]
        std = self.sc.robots[i].imu_noise
        return float(self.w[i] + (self.rng.normal(0, std) if std > 0 else 0.0))

    def close(self) -> None:
        try:
            p.disconnect(physicsClientId=self.cid)
        except p.error:
            pass
