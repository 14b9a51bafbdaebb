"""Angles and the formation's slot geometry (Bai 2022 eq. (3)). numpy and the standard library only."""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

__all__ = ["Slotlike", "polar", "polar_array", "slot_offset", "slot_position", "wrap", "wrap_array"]


_TAU = 2.0 * math.pi


def wrap(a: float) -> float:
    """Angle to (-pi, pi]: a itself when it is already there, else a - 2 pi k (k = floor((a + pi) / 2 pi)),
    with -pi folded to +pi. Only IEEE-exact operations, so :func:`wrap_array` gives the same bits on any
    platform (numpy's SIMD sin/cos/arctan2 may differ from the C library's by an ulp; this does not use them)."""
    a = float(a)
    if -math.pi < a <= math.pi:
        return a
    r = a - _TAU * math.floor((a + math.pi) / _TAU)
    return r if -math.pi < r <= math.pi else math.pi


def wrap_array(a) -> np.ndarray:
    """:func:`wrap` elementwise (the same values, bit for bit)."""
    a = np.asarray(a, float)
    inside = (a > -math.pi) & (a <= math.pi)
    r = np.where(inside, a, a - _TAU * np.floor((a + math.pi) / _TAU))
    return np.where((r > -math.pi) & (r <= math.pi), r, math.pi)


def polar(frm: tuple[float, float], yaw: float, to: tuple[float, float]) -> tuple[float, float]:
    """Distance [m] and bearing [rad, in the frame of a robot at ``frm`` heading ``yaw``] of the point ``to``."""
    dx, dy = to[0] - frm[0], to[1] - frm[1]
    return math.sqrt(dx * dx + dy * dy), wrap(math.atan2(dy, dx) - yaw)


def polar_array(x, y, yaw, tx, ty) -> tuple[np.ndarray, np.ndarray]:
    """:func:`polar` elementwise over broadcast arrays (the same distances bit for bit; the bearings to an ulp
    of numpy's arctan2 against the C library's, which may differ where numpy uses SIMD loops)."""
    dx, dy = np.asarray(tx, float) - x, np.asarray(ty, float) - y
    return np.sqrt(dx * dx + dy * dy), wrap_array(np.arctan2(dy, dx) - yaw)


class Slotlike(Protocol):
    """A follower's slot: ``L`` [m] and ``psi`` [rad, world frame] from the leader (stack.scenario.Slot)."""

    L: float
    psi: float


def slot_offset(slot: Slotlike) -> tuple[float, float]:
    """Eq. (3)'s offset of a slot from its leader: (L cos psi, L sin psi)."""
    return slot.L * math.cos(slot.psi), slot.L * math.sin(slot.psi)


def slot_position(leader_xy: tuple[float, float], slot: Slotlike) -> tuple[float, float]:
    """Bai 2022 eq. (3): x_F^g = x_L + L cos(psi), y_F^g = y_L + L sin(psi)."""
    dx, dy = slot_offset(slot)
    return leader_xy[0] + dx, leader_xy[1] + dy
