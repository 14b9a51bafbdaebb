"""A collision guard under every policy: never drive forward faster than the robot can still stop from.

Whatever a policy commands, the step caps the forward speed ``v`` so that the robot, braking at ``decel``
after ``lag_s`` (the scan's age when the command takes effect: one control period), stops before its
body grown by ``margin`` touches anything its newest scan sees along the path it is commanded onto: the
straight corridor ahead, or the arc of curvature ``w / v`` while it turns (a robot turning with forward
speed beside a box sweeps toward it). Rotation is never limited (a disc turning in place sweeps nothing
new) and neither is reversing. Like a base's own
collision monitor (Nav2's ``collision_monitor``, a Jackal's e-stop field), it is a safety layer, not a
planner: a robot it stops stays stopped until the policy turns it away, and a policy that keeps pushing
ahead is caught by the stuck detector (:mod:`.livelock`), which escapes or detours.

Geometry, in the robot frame (x ahead): a lidar end point ``(px, py)`` with ``|py| < R`` (``R = radius +
margin``) lies in the corridor the grown disc sweeps driving straight ahead; the disc touches it after
``D = px - sqrt(R^2 - py^2)`` metres. With the smallest such ``D``, the highest speed that still stops in
time solves ``v lag + v^2 / (2 decel) = D``: ``v = decel (sqrt(lag^2 + 2 D / decel) - lag)``.

On an arc of signed radius ``rho = v / w`` (centre ``(0, rho)``) the disc sweeps the ring of half-width
``R`` around the circle of radius ``|rho|``: a point at distance ``dc`` from the centre lies in it when
``delta = |dc - |rho|| < R``. With ``phi`` in (0, pi) the angle the robot turns about the centre to reach the
point's bearing, the disc's centre comes within ``R`` of it ``Delta`` earlier, ``cos Delta = (dc^2 + rho^2 -
R^2) / (2 dc |rho|)`` (the law of cosines), after the arc length ``D = |rho| (phi - Delta)``; negative when
the point is already within ``R`` and the arc brings the robot nearer (the straight corridor is the limit
``rho -> inf``). Capping ``v`` at a fixed ``w`` tightens the arc, so a capped speed
is found by bisection: the highest (to v / 4096) that stops in time on its own arc.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..settings import check, rule


STRAIGHT = 1e-3
"""[1/m] curvatures below this are judged as the straight corridor (a 1 km arc)."""
WAY_OUT_STEP = math.radians(5.0)
"""[rad] the headings :meth:`CollisionGuard.way_out` tries."""
ARC_ROUNDS = 12
"""Bisection rounds for a capped speed that is safe on its own (tighter) arc: to v / 4096."""
ROLLING = 0.02
"""[m/s] a base whose odometry says it moves forward faster than this is still rolling (:meth:`CollisionGuard.must_brake`)."""


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
    slide_after_s: float = field(default=1.0, metadata=rule(">= 0", "<= 60"))
    """[s] a robot the guard has held still this long while its policy asks to go forward takes the way out:
    it turns to the nearest heading whose straight corridor is free for ``slide_free`` and drives along it (the
    guard still judging), until the policy's own command is allowed again. 0: never (hold until the policy turns)."""
    slide_free: float = field(default=0.3, metadata=rule("> 0", "<= 5"))
    """[m] how far the way out must be free ahead of the grown disc."""

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
        self._ang, self._cos, self._sin = ang, np.cos(ang), np.sin(ang)
        self.capped = 0
        """Steps at which the guard lowered the policy's forward speed."""
        self.slides = 0
        """Steps at which the robot took the guard's way out (held still ``slide_after_s``, see the step)."""
        self.brakes = 0
        """Steps at which the whole command was zero: the base still rolled with something inside the margin ahead."""

    def free_distance(self, ranges: np.ndarray, curvature: float = 0.0) -> float:
        """How far the grown disc can drive ahead, straight or on an arc of ``curvature`` (w / v, left
        positive) [1/m], before it touches a lidar end point [m]; inf if nothing is in its way (negative:
        something is already inside the margin)."""
        r = np.asarray(ranges, float)
        if r.shape != self._cos.shape:
            return math.inf  # not the layout we know: judge nothing rather than misplace points
        hit = r < self.range_max - 1e-6
        px, py = r[hit] * self._cos[hit], r[hit] * self._sin[hit]
        if abs(curvature) < STRAIGHT:
            ahead = (px > 0.0) & (np.abs(py) < self.R)
            d = px[ahead] - np.sqrt(self.R ** 2 - py[ahead] ** 2)
        else:
            rho = 1.0 / curvature
            dc = np.hypot(px, py - rho)
            delta = np.abs(dc - abs(rho))  # from the circle the centre drives on
            turn = math.copysign(1.0, rho)  # +1: counter-clockwise about the centre (0, rho)
            phi = np.mod(turn * (np.arctan2(py - rho, px) + turn * math.pi / 2), 2 * math.pi)
            ahead = (delta < self.R) & (phi > 0.0) & (phi < math.pi)
            dc = dc[ahead]  # the disc's centre comes within R of the point Delta before its bearing (law of cosines)
            cos_c = (dc ** 2 + rho ** 2 - self.R ** 2) / np.maximum(2.0 * dc * abs(rho), 1e-12)
            d = abs(rho) * (phi[ahead] - np.arccos(np.clip(cos_c, -1.0, 1.0)))
        return float(d.min()) if d.size else math.inf

    def way_out(self, ranges: np.ndarray, prefer: float = 0.0) -> float | None:
        """The relative heading [rad] (within the lidar's field of view, in steps of ``WAY_OUT_STEP``) nearest to
        straight ahead whose straight corridor is free for ``slide_free``, on ``prefer``'s side when two are as near;
        None where none is."""
        r = np.asarray(ranges, float)
        if r.shape != self._cos.shape:
            return None
        hit = r < self.range_max - 1e-6
        ang, rr = self._ang[hit], r[hit]
        k = int(float(self._ang[-1]) / WAY_OUT_STEP + 1e-9) if len(self._ang) else 0
        theta = WAY_OUT_STEP * np.arange(-k, k + 1)  # straight ahead exactly 0.0 among them
        rel = ang[None, :] - theta[:, None]  # each point's bearing from each candidate heading
        px, py = rr[None, :] * np.cos(rel), rr[None, :] * np.sin(rel)
        inside = (px > 0.0) & (np.abs(py) < self.R)
        d = np.where(inside, px - np.sqrt(np.maximum(self.R ** 2 - py ** 2, 0.0)), np.inf).min(axis=1, initial=np.inf)
        ok = np.flatnonzero(d >= self.cfg.slide_free)
        if not len(ok):
            return None
        side = math.copysign(1.0, prefer) if prefer else 1.0
        best = min(ok, key=lambda k: (round(abs(theta[k]), 6), -side * theta[k]))
        return float(theta[best])

    def stoppable_speed(self, d: float) -> float:
        """The highest forward speed from which the robot stops within ``d`` metres."""
        if d <= 0.0:
            return 0.0
        a, lag = self.cfg.decel, self.cfg.lag_s
        return a * (math.sqrt(lag * lag + 2.0 * d / a) - lag)

    def must_brake(self, rolling: float, ranges: np.ndarray, w: float = 0.0) -> bool:
        """Whether the base, rolling forward at ``rolling`` (its odometry, whatever it was commanded), already has
        something inside the margin on its way (straight, or the arc ``w`` bends it onto): then the whole command
        must be zero, a straight brake (counted), until it has stopped. Capping ``v`` alone is not enough there: a
        drive whose wheels ramp at a bounded rate, commanded to turn in place one way and then the other, does not
        stop; each wheel swings between opposite targets and their mean, the forward speed, stays (an ``aina``
        leader chattering between (0.3, +1) and (0, -1) beside a box crept into it at 0.1 m/s for 2 s, its commanded
        ``v`` zero). Outside the margin the caps of :meth:`limit` keep it and the turn stays free (braking there too,
        wherever the odometry's speed exceeded the stoppable one, slowed a formation's followers near each other)."""
        if not self.cfg.enabled or rolling <= ROLLING:
            return False
        d = self.free_distance(ranges)
        if w != 0.0:
            d = min(d, self.free_distance(ranges, w / rolling))
        if d > 0.0:
            return False
        self.brakes += 1
        return True

    def limit(self, v: float, ranges: np.ndarray, w: float = 0.0) -> float:
        """``v`` capped to what the robot can stop from before what ``ranges`` shows on its way, straight or
        on the arc that ``w`` bends it onto (counted)."""
        if not self.cfg.enabled or v <= 0.0:
            return v

        def safe(u: float) -> bool:  # u stops in time on its own arc (curvature w / u)
            return u <= self.stoppable_speed(self.free_distance(ranges, w / u))

        if safe(v):
            return v
        self.capped += 1
        if w == 0.0:  # straight at any speed: the cap itself
            return self.stoppable_speed(self.free_distance(ranges))
        lo, hi = 0.0, v  # a lower v at the same w is a tighter arc: bisect for a speed safe on its own arc
        for _ in range(ARC_ROUNDS):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if safe(mid) else (lo, mid)
        return lo


__all__ = ["CollisionGuard", "GuardConfig"]
