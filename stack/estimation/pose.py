"""The pose type and angle wrapping shared by the estimators."""

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
