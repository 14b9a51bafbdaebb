"""Lidar sources: where a robot's scans come from (the sensor drivers' room; ``LIDARS`` in
``stack/drivers/__init__.py``), chosen by the scenario's ``robot.lidar.source``.

- ``world`` (``WorldLidar``): in simulation, the world publishes each robot's
  ``stack.comm.messages.Scan`` on ``stack/<fleet>/<id>/scan``, already in the robot's configured layout;
- a sensor on its own wire (``ros2``: ``sensor_msgs/LaserScan`` over Zenoh, ``rplidar``: a Slamtec
  A-series on a serial port): a ``Lidar``, the sensor-driver interface below. In simulation the world
  hosts a simulated device behind each (``stack/sim_bridge/lidar_devices.py``), so the same code runs.

The interface, like ``stack.drivers.base.Driver`` for bases: the public methods keep the rules and a
backend implements the underscored hooks::

    class MyLidar(Lidar):
        def _open(self): ...    # connect; return when the sensor streams (or raise LidarError)
        def _close(self): ...   # stop the sensor and release it
        # and, from its own thread, self._deliver(LidarScan(...)) for each whole scan

The rules: ``open`` / ``close`` once each (both safe to repeat; a context manager closes), ``read()`` the
newest scan, ``scans`` how many were delivered, ``counters`` (``count(name)``; a malformed one is also told
to ``on_malformed`` as ``<source>/<name>``), ``age()`` / ``liveness()`` on the source's clock (the agent's:
sim time in lock-step). Staleness itself is the agent's rule (``StepConfig.lidar_stale_s``).

A ``LidarScan`` is in the sensor's own frame (angles counter-clockwise from its forward axis, REP 103);
the agent turns it into the robot-centred beams its policy expects (``stack.agents.lidar.scan_from_lidar``,
with the ``robot.lidar.mount`` pose).
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..comm import Keys, receive
from ..comm.messages import Scan
from .base import Counted, Driver, DriverError

log = logging.getLogger(__name__)


class LidarError(DriverError):
    """A lidar that cannot open (no port, no answer, a sensor in protection stop): one line."""


@dataclass(frozen=True, eq=False)
class LidarScan:
    """One whole scan (a revolution, a ``LaserScan``) in the sensor's frame."""

    stamp: float
    """[s] the sensor's time of the scan: its header stamp, or the source's clock when the scan completed."""
    angles: np.ndarray
    """[rad] each sample's bearing, counter-clockwise from the sensor's forward axis (any order, any spacing)."""
    ranges: np.ndarray
    """[m] each sample's distance; NaN: an invalid sample (no measurement)."""
    range_max: float
    """[m] the sensor's longest range (a reading at or beyond it: no return)."""


class Lidar(Counted, ABC):
    """Base of every sensor source. ``on_scan(LidarScan)`` is called from the source's thread for each scan."""

    name = "base"
    config_class: type | None = None  # its settings dataclass (the scenario's ``robot.lidar.<source>`` block)

    def __init__(self, robot_id: int, *, clock: Callable[[], float] = time.monotonic,
                 on_scan: Callable[[LidarScan], None] | None = None,
                 on_malformed: Callable[[str], None] | None = None):
        self.robot_id = robot_id
        self._clock = clock
        self._on_scan = on_scan
        self._on_malformed = on_malformed or (lambda key: None)
        self._life = threading.Lock()
        self._books = threading.Lock()
        self._newest: LidarScan | None = None
        self._seen: float | None = None
        self.scans = 0
        self.counters: dict[str, int] = {}
        self.is_open = False

    def _configure(self, config, params: dict):
        """``config`` (or the defaults) with the scenario's ``params`` over it; unknown ones are a one-line error."""
        return Driver._configure(self, config, params)

    # --- lifecycle ---------------------------------------------------------------------
    def open(self) -> "Lidar":
        with self._life:
            if not self.is_open:
                with self._books:
                    self._newest, self._seen = None, None
                self._open()
                self.is_open = True
        return self

    def close(self) -> None:
        with self._life:
            if self.is_open:
                self.is_open = False
                self._close()

    def __enter__(self) -> "Lidar":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- scans -------------------------------------------------------------------------
    def read(self) -> LidarScan | None:
        """The newest scan, or None before the first."""
        with self._books:
            return self._newest

    def _deliver(self, scan: LidarScan) -> None:
        """A whole scan (the backend's thread): kept as the newest, counted, handed to ``on_scan``."""
        with self._books:
            self._newest, self._seen = scan, self._clock()
            self.scans += 1
            self.counters["scan"] = self.counters.get("scan", 0) + 1
        if self._on_scan is not None:
            self._on_scan(scan)

    # --- counters and liveness -----------------------------------------------------------
    def age(self, now: float | None = None) -> float | None:
        """Seconds on the source's clock since the newest scan; None before the first."""
        with self._books:
            seen = self._seen
        return None if seen is None else (self._clock() if now is None else now) - seen

    def liveness(self, now: float | None = None) -> dict[str, float]:
        age = self.age(now)
        return {} if age is None else {"scan": age}

    # --- backend hooks ---------------------------------------------------------------------
    @abstractmethod
    def _open(self) -> None:
        """Backend: open the sensor and start delivering its scans; raise ``LidarError`` saying why it cannot."""

    @abstractmethod
    def _close(self) -> None:
        """Backend: stop the sensor and release it."""


class WorldLidar:
    """The world's scans for one robot: each well-formed one for this robot goes to ``on_scan``;
    the rest are counted through ``on_malformed(key)``. (The agent reads these itself, step by step.)"""

    def __init__(self, robot_id: int, *, session, keys: Keys, on_scan: Callable[[Scan], None],
                 on_malformed: Callable[[str], None] | None = None):
        self.robot_id, self._on_scan, self._on_malformed = robot_id, on_scan, on_malformed
        self._key = keys.robot(robot_id, "scan")
        self._sub = session.declare_subscriber(self._key, self._deliver)

    def _deliver(self, sample) -> None:
        m = receive(sample, Scan, self._on_malformed)
        if m is None:
            return
        if m.id != self.robot_id:
            if self._on_malformed is not None:
                self._on_malformed(self._key)
            return
        self._on_scan(m)

    def close(self) -> None:
        self._sub.undeclare()


def make_lidar(source: str, robot_id: int, **kw) -> Lidar:
    """The sensor source ``source`` (a ``LIDARS`` record other than ``world``) for robot ``robot_id``."""
    from . import LIDARS

    if source == "world":
        raise LidarError("the world's lidar is read by the agent itself (no sensor driver)")
    try:
        cls = LIDARS[source].make()
    except LookupError as e:
        raise LidarError(str(e)) from None
    return cls(robot_id, **kw)


__all__ = ["Lidar", "LidarError", "LidarScan", "WorldLidar", "make_lidar"]
