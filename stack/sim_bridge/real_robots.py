"""The world's side of the robots that live outside it (``robots[i].embodiment: real``): mixed reality.

A real robot is not simulated. Its agent runs where the robot is, on the robot's own driver; the world
keeps a body for it at the pose its ``pose_source`` gives (its published estimate, the ``state`` it sends
every control step, or a motion-capture system's ``geometry_msgs/PoseStamped`` on a Zenoh key), so the
simulated robots' lidars, the collision measures and the report see it where it is.

Each world step (:meth:`RealRobots.place`) every real robot's body moves to its newest pose. A pose older
than ``pose_source.stale_after_s`` (the world's clock, from its arrival) is stale: the body stays at the last
pose and grows by the distance the robot could have driven since at ``v_max`` (at most
``STALE_GROWTH_MAX_M``): the simulated robots' lidars, hence their guards, give the robot that berth, and
the truth marks it stale. A fresh pose brings the body back to its size.

A real robot with ``lidar.virtual`` gets a virtual scan each step (``stack/<fleet>/<id>/virtual_scan``, a
``Scan`` of its configured layout): its beams cast from its body against the virtual bodies only (simulated
robots, obstacles marked ``virtual``); its agent merges them into its real scan (``stack.agents.virtual``).
While its pose is stale no virtual scan goes out (it would be cast from a pose nobody trusts).

A payload that does not decode is dropped and counted per key in ``malformed`` (and in the world's own count).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque

import zenoh

from ..comm import Keys, MessageError, decode, encode
from ..comm.messages import Scan, State
from ..drivers.ros2cdr import CdrError, decode_pose_stamped

log = logging.getLogger("stack.world")

STALE_GROWTH_MAX_M = 1.0
"""[m] the most a stale real robot's body grows."""
SPEED_BASELINE_S = 0.1
"""[s] a motion-capture body's speed is taken over at least this much capture time (the newest pose against the
oldest kept)."""
GROWTH_STEP_M = 0.05
"""[m] the body's growth is rounded up to this (its collision shape is rebuilt when it changes)."""


class RealRobots:
    """The real robots of one world: their pose sources (subscribed on ``session``), bodies and virtual scans."""

    def __init__(self, world, scenario, session: zenoh.Session, keys: Keys, clock=time.monotonic):
        self.world, self.keys, self.clock = world, keys, clock
        self.robots = {r.id: r for r in scenario.robots if r.embodiment == "real"}
        self._lock = threading.Lock()
        self.latest: dict[int, tuple[float, float, float, float, float, float]] = {}  # id -> x, y, yaw, v, w, arrival
        self.poses: Counter[int] = Counter()
        self._history: dict[int, deque] = {}  # motion capture: (stamp, x, y, yaw) over SPEED_BASELINE_S of stamps
        self._speed: dict[int, tuple[float, float]] = {}  # motion capture: (v, w) over that baseline
        self.malformed: Counter[str] = Counter()
        self.out_of_order: Counter[int] = Counter()  # motion capture: poses stamped before one already taken
        self.stale_since: dict[int, float] = {}  # id -> sim time its pose went stale
        self.stale_spans: list[dict] = []  # {"robot", "start", "end"} in sim time
        self.virtual_sent: Counter[int] = Counter()
        self._subs = [self._subscribe(session, rid, r) for rid, r in self.robots.items()]

    def source_of(self, rid: int) -> str:
        """Where robot ``rid``'s pose comes from, in words for the report and errors."""
        key = self.robots[rid].pose_source.key
        return f"PoseStamped on {key!r}" if key else f"its estimate on {self.keys.robot(rid, 'state')!r}"

    def _subscribe(self, session: zenoh.Session, rid: int, robot):
        key = robot.pose_source.key
        if key is None:
            return session.declare_subscriber(self.keys.robot(rid, "state"), lambda s, rid=rid: self._on_state(rid, s))
        return session.declare_subscriber(key, lambda s, rid=rid: self._on_pose(rid, s))

    def _on_state(self, rid: int, sample: zenoh.Sample) -> None:
        try:
            m = decode(sample.payload.to_bytes(), State)
            if m.id != rid:
                raise MessageError(f"state of robot {m.id} on robot {rid}'s key")
        except MessageError:
            return self._bad(str(sample.key_expr))
        self._took(rid, (m.x, m.y, m.yaw, m.v, m.w))

    def _on_pose(self, rid: int, sample: zenoh.Sample) -> None:
        try:
            stamp, x, y, yaw = decode_pose_stamped(sample.payload.to_bytes())
        except CdrError:
            return self._bad(str(sample.key_expr))
        with self._lock:
            v, w = self._speed.get(rid, (0.0, 0.0))
            hist = self._history.setdefault(rid, deque())
            if hist and stamp < hist[-1][0] - 1e-4:  # older than one taken: counted, not placed
                self.out_of_order[rid] += 1
                return
            if hist and stamp <= hist[-1][0] + 1e-4:  # one capture stamp twice: the later arrival stands
                hist.pop()
            hist.append((stamp, x, y, yaw))
            while len(hist) > 2 and hist[-1][0] - hist[1][0] >= SPEED_BASELINE_S:
                hist.popleft()
            # the body's speed (the truth's, the world's settle check): over at least SPEED_BASELINE_S of capture
            # stamps, not arrivals (samples come in bursts) and not the last two poses (10 ms apart at 100 Hz, where
            # a millimetre of jitter, or a pose that repeats, reads as 0.1 m/s or as standing still)
            t0, x0, y0, yaw0 = hist[0]
            if stamp - t0 > 1e-4:
                v = math.hypot(x - x0, y - y0) / (stamp - t0)
                w = math.remainder(yaw - yaw0, math.tau) / (stamp - t0)
                self._speed[rid] = (v, w)
        self._took(rid, (x, y, yaw, v, w))

    def _took(self, rid: int, pose: tuple[float, float, float, float, float]) -> None:
        with self._lock:
            self.latest[rid] = (*pose, self.clock())
            self.poses[rid] += 1

    def _bad(self, key: str) -> None:
        with self._lock:
            self.malformed[key] += 1

    def waiting_for(self) -> list[int]:
        """The real robots no pose has come from yet."""
        with self._lock:
            return sorted(set(self.robots) - set(self.latest))

    def place(self, t: float) -> list[int]:
        """Each real robot's body at its newest pose (grown if stale); the robots whose pose is stale now."""
        now, stale = self.clock(), []
        with self._lock:
            latest = dict(self.latest)
        for rid, robot in self.robots.items():
            if rid not in latest:
                continue
            x, y, yaw, v, w, at = latest[rid]
            age = now - at
            if age <= robot.pose_source.stale_after_s:
                self.world.place(rid, x, y, yaw, v, w)
                self.world.set_radius(rid, robot.radius)
                self._fresh(rid, t)
                continue
            stale.append(rid)
            grow = min(robot.v_max * (age - robot.pose_source.stale_after_s), STALE_GROWTH_MAX_M)
            self.world.place(rid, x, y, yaw, 0.0, 0.0)
            self.world.set_radius(rid, robot.radius + math.ceil(grow / GROWTH_STEP_M) * GROWTH_STEP_M)
            if rid not in self.stale_since:
                self.stale_since[rid] = t
                self.stale_spans.append({"robot": rid, "start": t, "end": None})
                log.warning("world: t=%.1f s: real robot %d: no pose for %.1f s (%s): stale", t, rid, age,
                            self.source_of(rid))
        return stale

    def _fresh(self, rid: int, t: float) -> None:
        if self.stale_since.pop(rid, None) is not None:
            for span in self.stale_spans:
                if span["robot"] == rid and span["end"] is None:
                    span["end"] = t
            log.warning("world: t=%.1f s: real robot %d: pose back", t, rid)

    def publish_virtual(self, pubs: dict, step: int, stamp: float, stale: list[int]) -> None:
        """The virtual scan of every real robot with ``lidar.virtual`` whose pose is fresh."""
        for rid, robot in self.robots.items():
            if not robot.lidar.virtual or rid in stale or rid not in self.latest:
                continue
            lid = robot.lidar
            inc = lid.fov / (lid.beams - 1) if lid.beams > 1 else 0.0
            scan = Scan(id=rid, step=step, stamp=stamp, angle_min=-lid.fov / 2 if lid.beams > 1 else 0.0,
                        angle_increment=inc, range_max=lid.range, ranges=self.world.virtual_scan(rid).tolist())
            pubs[rid].put(encode(scan))
            self.virtual_sent[rid] += 1

    def report(self) -> dict:
        """For ``world.json``: who was real, where each pose came from, how many, the stale spans, drops."""
        with self._lock:
            return {"real_robots": sorted(self.robots),
                    "pose_sources": {str(rid): self.robots[rid].pose_source.key or "estimate" for rid in self.robots},
                    "poses_received": {str(rid): self.poses[rid] for rid in self.robots},
                    "pose_stale": [dict(s) for s in self.stale_spans],
                    "virtual_scans_sent": {str(rid): self.virtual_sent[rid] for rid in self.robots
                                           if self.robots[rid].lidar.virtual},
                    "pose_malformed": dict(self.malformed),
                    "pose_out_of_order": {str(rid): n for rid, n in self.out_of_order.items()}}

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs = []
