"""The pose type shared by the estimators, and the angle wrap (the one copy in :mod:`stack.models.geometry`)."""

from __future__ import annotations

from dataclasses import dataclass

from ..models.geometry import wrap

__all__ = ["Pose", "wrap"]


@dataclass
class Pose:
    x: float
    y: float
    yaw: float
    v: float = 0.0
    w: float = 0.0

