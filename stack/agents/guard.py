"""A collision guard under every policy: never drive forward faster than the robot can still stop from.

Whatever a policy commands, the step caps the forward speed ``v`` so that the robot, braking at ``decel``
after ``lag_s`` (the scan's age when the command takes effect: one control period), stops before its
body grown by ``margin`` touches anything its newest scan sees in the straight corridor ahead. Rotation is
never limited (a disc turning in place sweeps nothing new) and neither is reversing. Like a base's own
collision monitor (Nav2's ``collision_monitor``, a Jackal's e-stop field), it is a safety layer, not a
planner: a robot it stops stays stopped until the policy turns it away, and a policy that keeps pushing
ahead is caught by the stuck detector (:mod:`.livelock`), which escapes or detours.

Geometry, in the robot frame (x ahead): a lidar end point ``(px, py)`` with ``|py| < R`` (``R = radius +
margin``) lies in the corridor the grown disc sweeps driving straight ahead; the disc touches it after
``D = px - sqrt(R^2 - py^2)`` metres. With the smallest such ``D``, the highest speed that still stops in
time solves ``v lag + v^2 / (2 decel) = D``: ``v = decel (sqrt(lag^2 + 2 D / decel) - lag)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..settings import check, rule


@dataclass
class GuardConfig:
    """The guard's settings (``StepConfig.guard``)."""

    margin: float = field(default=0.1, metadata=rule(">= 0", "<= 2"))
    """[m] kept between the robot's body and anything the lidar sees ahead."""
    decel: float = field(default=1.0, metadata=rule("> 0"))
    """[m/s^2] the braking the guard counts on (below what the bases do: the world's default is 3 m/s^2)."""
    lag_s: float = field(default=0.1, metadata=rule(">= 0", "<= 2"))
    """[s] from the scan to the robot braking (a control period, the command's trip to the base)."""
    enabled: bool = True
    """False: the policy's speed goes out as it is (to measure a policy alone)."""

    def __post_init__(self) -> None:
        check(self)


class CollisionGuard:
    """Caps a command's forward speed by the free distance ahead in a scan of ``beams`` beams evenly over
    ``-fov/2 .. fov/2`` (the layout the agent resamples every lidar to), ranges from the robot's centre."""

    def __init__(self, radius: float, fov: float, beams: int, range_max: float, cfg: GuardConfig | None = None):
        self.cfg = cfg or GuardConfig()
        self.R = radius + self.cfg.margin
        self.range_max = range_max
        ang = np.linspace(-fov / 2, fov / 2, beams) if beams > 1 else np.zeros(beams)
        self._cos, self._sin = np.cos(ang), np.sin(ang)
        self.capped = 0
        """Steps at which the guard lowered the policy's forward speed."""

    def free_distance(self, ranges: np.ndarray) -> float:
        """How far the grown disc can drive straight ahead before it touches a lidar end point [m]; inf if
        nothing is in its way (negative: something is already inside the margin)."""
        r = np.asarray(ranges, float)
        if r.shape != self._cos.shape:
            return math.inf  # not the layout we know: judge nothing rather than misplace points
        hit = r < self.range_max - 1e-6
        px, py = r * self._cos, r * self._sin
        ahead = hit & (px > 0.0) & (np.abs(py) < self.R)
        if not ahead.any():
            return math.inf
        return float(np.min(px[ahead] - np.sqrt(self.R ** 2 - py[ahead] ** 2)))

    def stoppable_speed(self, d: float) -> float:
        """The highest forward speed from which the robot stops within ``d`` metres."""
        if d <= 0.0:
            return 0.0
        a, lag = self.cfg.decel, self.cfg.lag_s
        return a * (math.sqrt(lag * lag + 2.0 * d / a) - lag)

    def limit(self, v: float, ranges: np.ndarray) -> float:
        """``v`` capped to what the robot can stop from before what ``ranges`` shows ahead (counted)."""
        if not self.cfg.enabled or v <= 0.0:
            return v
        cap = self.stoppable_speed(self.free_distance(ranges))
        if v > cap:
            self.capped += 1
            return cap
        return v


__all__ = ["CollisionGuard", "GuardConfig"]
