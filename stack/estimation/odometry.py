"""Dead reckoning: integrate wheel odometry with the unicycle model, Bai 2022 eq. (1).

The stand-in estimator until the filterpy EKF lands (issue 4): it drifts with odometry
noise, which is the point of that issue.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class Pose:
    x: float
    y: float
    yaw: float
    v: float = 0.0
    w: float = 0.0


def wrap(a: float) -> float:
    """Angle to (-pi, pi]."""
    a = math.atan2(math.sin(a), math.cos(a))
    return a if a > -math.pi else math.pi


class OdometryIntegrator:
    """x' = v cos(phi), y' = v sin(phi), phi' = w  (eq. 1), integrated exactly over one period."""

    def __init__(self, x: float, y: float, yaw: float):
        self.pose = Pose(x, y, wrap(yaw))

    def update(self, v: float, w: float, dt: float) -> Pose:
        if not (math.isfinite(v) and math.isfinite(w) and math.isfinite(dt)) or dt <= 0:
            return self.pose  # a NaN never reaches the state
        p = self.pose
        if abs(w) < 1e-9:
            p.x += v * dt * math.cos(p.yaw)
            p.y += v * dt * math.sin(p.yaw)
        else:  # exact arc
            p.x += v / w * (math.sin(p.yaw + w * dt) - math.sin(p.yaw))
            p.y -= v / w * (math.cos(p.yaw + w * dt) - math.cos(p.yaw))
        p.yaw = wrap(p.yaw + w * dt)
        p.v, p.w = v, w
        return p
