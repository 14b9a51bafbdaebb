"""Frames and clocks of a robot's own streams: the transform site <- odom, and device stamps on the agent's clock.

Frames. A driver reports odometry in its device's own frame (``Odometry.pose``: the base's dead-reckoned pose
in its odom frame; a Jackal's odom frame is (0, 0, 0) where it booted). The agent estimates in the site frame
(the scenario's frame: a robot's ``pose`` is its start pose in it) and keeps the transform site <- odom,
``OdomFrame``. Where that transform comes from is the robot's ``odom_origin``:

- ``boot``: the odom frame's origin is the robot's start pose (the device booted there): T = start pose.
  Right at a fresh start and after an agent restart alike (the device did not reboot, its odom frame is the
  one it booted with); the hardware case.
- ``boot-position``: the odom frame's origin is the robot's start position, its axes the site's: T = (x0, y0, 0).
  An ArduPilot vehicle whose EKF origin is where it booted: ``LOCAL_POSITION_NED`` is north/east of that origin,
  its heading is absolute. Right at a fresh start and after a restart, as ``boot``.
- ``site``: the odom frame is the site frame: T = identity. Today's simulated devices (world-frame odometry),
  a rover whose EKF origin is the site datum. Right at a fresh start and after a restart.
- ``first``: the robot is at its start pose at the agent's first sample, whatever its odom frame:
  T = start pose * inverse(first sample's pose). Right for any device at a fresh start; not after a restart
  (the robot has moved since): a restarted agent then takes its start from the fixes.

Position fixes refine the transform: after each fix the estimator's site pose and the newest odom pose give
T again (``refine``), so the transform follows the odometry's drift.

Clocks. ``StreamClock`` puts a stream's device stamps onto the agent's monotonic clock: the interval between
two samples is the stamps' (the device measured it, free of transport jitter) where the device clock is
usable (stamps that advance and agree with the arrivals within ``max_skew_s``); the arrival interval where it
is not (a stamp that stands still, goes back, or jumps: another host's clock, a driver that stamps nothing).
A constant offset between the device's clock and ours (seconds, another host) does not matter: only
intervals are taken from the stamps, and each sample's time is never later than its arrival.
"""

from __future__ import annotations

import math

from ..estimation.pose import wrap

ODOM_ORIGINS = ("site", "boot", "boot-position", "first")

Pose2 = tuple[float, float, float]


def compose(a: Pose2, b: Pose2) -> Pose2:
    """a * b: pose ``b`` given in frame ``a``, expressed in ``a``'s parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2])


def inverse(a: Pose2) -> Pose2:
    c, s = math.cos(a[2]), math.sin(a[2])
    return -c * a[0] - s * a[1], s * a[0] - c * a[1], wrap(-a[2])


class OdomFrame:
    """The transform site <- odom of one robot (see the module docstring for ``origin``)."""

    def __init__(self, start: Pose2, origin: str = "site"):
        if origin not in ODOM_ORIGINS:
            raise ValueError(f"odom_origin: expected one of {', '.join(ODOM_ORIGINS)}, got {origin!r}")
        self.start = tuple(float(v) for v in start)
        self.origin = origin
        self.T: Pose2 | None = None

    def site_pose(self, odom_pose: Pose2 | None) -> Pose2:
        """The site pose of the first sample (fixing T by the rule); later ones map through T."""
        if self.T is None:
            if odom_pose is None:  # a base without a pose (CAN encoders): it starts at its start pose
                return self.start
            if self.origin == "site":
                self.T = (0.0, 0.0, 0.0)
            elif self.origin == "boot":
                self.T = self.start
            elif self.origin == "boot-position":
                self.T = (self.start[0], self.start[1], 0.0)
            else:
                self.T = compose(self.start, inverse(odom_pose))
        return self.start if odom_pose is None else compose(self.T, odom_pose)

    def refine(self, site: Pose2, odom_pose: Pose2 | None) -> None:
        """A fix moved the site estimate: T follows (site = T * odom)."""
        if odom_pose is not None:
            self.T = compose(site, inverse(odom_pose))


class StreamClock:
    """One stream's sample times on the agent's clock, from device stamps where they are usable."""

    def __init__(self, max_skew_s: float = 0.25):
        self.max_skew_s = max_skew_s
        self._stamp: float | None = None
        self._arrival = 0.0
        self._t = 0.0
        self.unusable = 0  # samples timed by their arrival because the stamp was not usable

    def time_of(self, stamp: float, arrival: float) -> float:
        """The time (agent clock) a sample stamped ``stamp`` (device clock) that arrived at ``arrival`` was taken."""
        prev, self._stamp = self._stamp, stamp
        if prev is None:
            t = arrival
        else:
            d_stamp, d_arrival = stamp - prev, arrival - self._arrival
            if math.isfinite(d_stamp) and d_stamp > 0 and abs(d_stamp - d_arrival) <= self.max_skew_s:
                # the device's interval; never later than its arrival, never more than max_skew_s before it
                t = max(arrival - self.max_skew_s, min(self._t + d_stamp, arrival))
            else:
                self.unusable += 1
                t = arrival
        self._arrival, self._t = arrival, t
        return t
