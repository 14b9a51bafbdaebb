"""The differential drive and the unicycle's exact arc (Bai 2022 eq. (1) over one period).

    x' = v cos(yaw),  y' = v sin(yaw),  yaw' = w

With v and w constant over dt the robot drives a circular arc whose chord has length
v dt sinc(w dt / 2) and heading yaw + w dt / 2; that form is exact for any w and needs no
special case at w = 0 (the quotient v / w (sin(yaw + w dt) - sin(yaw)) loses its digits as w -> 0).

Two forms: :func:`arc_step` on floats (the EKF, one robot) and :func:`arc_step_array` on numpy
arrays (the worlds, every robot at once). They are the same formula and give the same numbers
(``tests/test_models.py`` checks it). The wheel maps work on floats and arrays alike.
"""

from __future__ import annotations

import math

import numpy as np

from .geometry import wrap, wrap_array

__all__ = ["arc_step", "arc_step_array", "body_rates", "ramp", "sinc", "sinc_array", "wheel_speeds"]

_SMALL = 1e-3  # |h| below this: sinc by its Taylor series (no 0/0, and no cancellation)


def sinc(h: float) -> tuple[float, float]:
    """sin(h)/h and its derivative, with their Taylor series near 0."""
    if abs(h) < _SMALL:
        h2 = h * h
        return 1.0 - h2 / 6.0 + h2 * h2 / 120.0, -h / 3.0 + h * h2 / 30.0
    s, c = math.sin(h), math.cos(h)
    return s / h, (h * c - s) / (h * h)


def sinc_array(h) -> np.ndarray:
    """sin(h)/h elementwise (the value of :func:`sinc`)."""
    h = np.asarray(h, float)
    small = np.abs(h) < _SMALL
    h2 = h * h
    hs = np.where(small, 1.0, h)
    return np.where(small, 1.0 - h2 / 6.0 + h2 * h2 / 120.0, np.sin(hs) / hs)


def arc_step(x: float, y: float, yaw: float, v: float, w: float, dt: float) -> tuple[float, float, float]:
    """The pose after dt at constant (v, w): the exact arc; yaw wrapped to (-pi, pi]."""
    h = 0.5 * w * dt
    chord, m = v * dt * sinc(h)[0], yaw + h
    return x + chord * math.cos(m), y + chord * math.sin(m), wrap(yaw + w * dt)


def arc_step_array(x, y, yaw, v, w, dt) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`arc_step` elementwise over broadcast arrays."""
    h = 0.5 * np.asarray(w, float) * dt
    chord, m = v * dt * sinc_array(h), yaw + h
    return x + chord * np.cos(m), y + chord * np.sin(m), wrap_array(yaw + w * dt)


def wheel_speeds(v, w, track, wheel_radius):
    """Inverse kinematics: wheel angular speeds (left, right) [rad/s] for body rates (v, w)."""
    return (v - w * track / 2) / wheel_radius, (v + w * track / 2) / wheel_radius


def body_rates(wl, wr, track, wheel_radius):
    """Forward kinematics: body rates (v [m/s], w [rad/s]) from wheel angular speeds (left, right)."""
    return wheel_radius * (wr + wl) / 2, wheel_radius * (wr - wl) / track


def ramp(current, target, dmax):
    """``current`` moved toward ``target`` by at most ``dmax`` (an acceleration limit over one period)."""
    return current + np.clip(target - current, -dmax, dmax)
