"""A real robot's view of the virtual ones: the world's virtual returns merged into its real scan.

A real robot (``robots[i].embodiment: real``) with ``robot.lidar.virtual: true`` hears a virtual scan from the
fleet's world each world step (``stack/<fleet>/<id>/virtual_scan``): its configured beams cast from where its
pose source put it, against the bodies that exist only in the world (simulated robots, obstacles marked
``virtual``). Per beam the nearer return wins (:meth:`VirtualReturns.merge`), so the policy, the guard and the
stuck detector see the virtual robots as they see the real ones. Each merged return (a beam the virtual
scan shortened) is counted.

The rule when the virtual side goes stale: a virtual scan older than ``lidar.virtual_timeout`` (the agent's
clock, from its arrival) is not merged; from then, until a fresh one comes, the robot drives on its real scan
alone and its forward speed is held to at most ``lidar.virtual_lost_speed`` (the virtual robots are still
somewhere; it can no longer see them). Nothing stale is merged, ever: a lost world leaves no virtual
obstacle behind. The span lost is counted in steps.

A virtual scan of another robot or of another layout is dropped and counted as malformed, as every bad
sample is.
"""

from __future__ import annotations

import threading

import numpy as np

from ..comm.messages import Scan


class VirtualReturns:
    """The newest virtual scan of one robot, merged into its real scans while it is fresh."""

    def __init__(self, robot):
        self.robot = robot
        self.timeout = robot.lidar.virtual_timeout
        self.lost_speed = robot.lidar.virtual_lost_speed
        self._lock = threading.Lock()
        self._newest: tuple[np.ndarray, float] | None = None  # ranges, arrival (agent clock)
        self.seen = False  # a virtual scan has come (before that, nothing is lost)
        self.received = 0
        self.merged_scans = 0
        self.merged_returns = 0  # beams the virtual scan shortened
        self.lost_steps = 0  # steps the virtual side was stale (speed held)
        self.lost_since: float | None = None

    def accept(self, scan: Scan, now: float) -> None:
        """A virtual scan from the world; ValueError if it is not for this robot's configured lidar."""
        lid = self.robot.lidar
        if scan.id != self.robot.id or len(scan.ranges) != lid.beams or abs(scan.range_max - lid.range) > 1e-9:
            raise ValueError("virtual scan for another robot or another lidar layout")
        with self._lock:
            self._newest = (np.asarray(scan.ranges, float), now)
            self.seen = True
            self.received += 1

    def merge(self, scan: Scan, now: float) -> Scan:
        """``scan`` with the fresh virtual returns merged in (the nearer return per beam); as it is when stale."""
        with self._lock:
            newest = self._newest
        if newest is None or now - newest[1] > self.timeout:
            return scan
        real = np.asarray(scan.ranges, float)
        ranges = np.minimum(real, newest[0])
        shortened = int(np.count_nonzero(ranges < real))
        self.merged_scans += 1
        self.merged_returns += shortened
        if shortened == 0:
            return scan
        return Scan(id=scan.id, step=scan.step, stamp=scan.stamp, angle_min=scan.angle_min,
                    angle_increment=scan.angle_increment, range_max=scan.range_max, ranges=ranges.tolist())

    def lost(self, now: float) -> bool:
        """Whether the virtual side is lost now: seen before, nothing fresh since ``virtual_timeout``."""
        with self._lock:
            newest = self._newest
        gone = self.seen and (newest is None or now - newest[1] > self.timeout)
        self.lost_since = (self.lost_since if self.lost_since is not None else now) if gone else None
        return gone

    def hold(self, v: float, w: float, now: float) -> tuple[float, float]:
        """The command to send: forward speed held to ``virtual_lost_speed`` while the virtual side is lost."""
        if not self.lost(now):
            return v, w
        self.lost_steps += 1
        return min(v, self.lost_speed), w

    def counters(self) -> dict[str, int]:
        return {"received": self.received, "merged_scans": self.merged_scans, "merged_returns": self.merged_returns,
                "lost_steps": self.lost_steps}
