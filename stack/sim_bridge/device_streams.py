"""What a hardware-like simulated device needs to send at its own rate: sample times, losses, poses in between.

A real sensor samples on its own clock at its own rate, not once per world step: ``Stream``
gives the sample times that fall in a world step (lock-step: the device sends them when the
step ends, each at its own time), with the device's jitter and losses, seeded so lock-step
runs repeat. ``arc`` moves a pose along the unicycle arc the world moved the body on over the
step (the world holds (v, w) constant within a step), so a sample inside a step sees the body
where it was then. ``relative_pose`` puts a world pose in a frame that starts at another pose
(an odom frame that is (0, 0, 0) where the robot booted).
"""

from __future__ import annotations

import math

import numpy as np


def wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def arc(pose: tuple[float, float, float], v: float, w: float, dt: float) -> tuple[float, float, float]:
    """The pose after ``dt`` at constant (v, w): the world's exact arc (``World.step``)."""
    x, y, th = pose
    if abs(w) < 1e-9:
        return x + v * dt * math.cos(th), y + v * dt * math.sin(th), wrap(th + w * dt)
    return (x + v / w * (math.sin(th + w * dt) - math.sin(th)), y - v / w * (math.cos(th + w * dt) - math.cos(th)),
            wrap(th + w * dt))


def relative_pose(origin: tuple[float, float, float], pose: tuple[float, float, float]) -> tuple[float, float, float]:
    """``pose`` (world frame) in the frame whose origin is ``origin`` (world frame): origin^-1 * pose."""
    ox, oy, oth = origin
    dx, dy = pose[0] - ox, pose[1] - oy
    c, s = math.cos(oth), math.sin(oth)
    return c * dx + s * dy, -s * dx + c * dy, wrap(pose[2] - oth)


class Stream:
    """The sample schedule of one sensor stream: nominal times n / rate_hz (sim time from 0), each moved by
    the device's jitter (normal, std ``jitter_s``, clipped to 0.45 of a period so samples keep their order)
    and lost with probability ``drop_prob`` (a sample lost on the wire: the device still took it)."""

    def __init__(self, rate_hz: float, *, jitter_s: float = 0.0, drop_prob: float = 0.0,
                 rng: np.random.Generator | None = None):
        self.period = 1.0 / rate_hz
        self.jitter_s = jitter_s
        self.drop_prob = drop_prob
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self._next = 0  # index of the next nominal sample to draw
        self._pending: tuple[float, bool] | None = None  # drawn, not yet due
        self.sent = 0
        self.dropped = 0

    def due(self, t_end: float, *, inclusive: bool = True) -> list[tuple[float, bool]]:
        """(time, kept) of every sample taken at or before ``t_end`` (before, with ``inclusive=False``) and not
        yet given, in order; ``kept`` False: lost on the wire."""
        out = []
        eps = 1e-9 * max(1.0, abs(t_end))
        while True:
            if self._pending is None:
                self._pending = self._draw()
            t, kept = self._pending
            if t > t_end + eps or (not inclusive and t >= t_end - eps):
                return out
            self._pending = None
            self.sent += kept
            self.dropped += not kept
            out.append((t, kept))

    def _draw(self) -> tuple[float, bool]:
        t = self._next * self.period
        self._next += 1
        if self.jitter_s > 0:
            t += float(np.clip(self.rng.normal(0.0, self.jitter_s), -0.45 * self.period, 0.45 * self.period))
        kept = not (self.drop_prob > 0 and self.rng.random() < self.drop_prob)
        return max(t, 0.0), kept

    def restart(self, t: float) -> None:
        """The schedule goes on from ``t`` (the first sample at the first tick at or after it): the device's
        clock changed hands (real time to lock-step); the counts start again."""
        self._pending = None
        self.sent = self.dropped = 0
        self._next = max(0, math.ceil(t / self.period - 1e-9))

    @property
    def next_time(self) -> float:
        """Time of the next sample (drawn now if need be)."""
        if self._pending is None:
            self._pending = self._draw()
        return self._pending[0]


__all__ = ["Stream", "arc", "relative_pose", "wrap"]
