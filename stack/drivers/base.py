"""The driver interface: ``open / command(v, w) / read / close``.

Like python-can's ``BusABC``: the public methods keep the rules (clamping to the robot's
limits, eq. (2) of Bai 2022; the command watchdog; zero velocity before closing) and a
backend implements only the underscored hooks::

    class MyDriver(Driver):
        def _open(self): ...
        def _send(self, v, w): ...      # put one (already clamped) command on the wire
        def _read(self): ...            # newest Odometry or None
        def _close(self): ...

A driver is a context manager; leaving the block commands zero and closes.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields, replace
from typing import Callable

log = logging.getLogger(__name__)


class DriverError(RuntimeError):
    """A driver that cannot open, or a device fault (the agent stops the robot and reports it)."""


@dataclass(frozen=True)
class Odometry:
    """Wheel odometry as the driver measured it: body-frame speeds, their time and step."""

    v: float
    w: float
    stamp: float
    step: int = -1
    wz_imu: float | None = None  # gyro yaw rate, where the base has one
    pose: tuple[float, float, float] | None = None  # the base's own dead-reckoned (x, y, yaw), where it has one


@dataclass(frozen=True)
class DriverLimits:
    v_max: float
    w_max: float
    cmd_timeout: float = 0.5  # [s] a command older than this is replaced by zero


class Periodic:
    """Something a device needs at least every ``period`` (a keep-alive, a GCS heartbeat).

    Due when ``period`` has passed on the driver's clock *or* on the wall clock. In lock-step
    the driver's clock is sim time, which stands still while the world waits for the fleet and
    may run faster than the wall once it steps; the device behind the wire (its watchdog, its
    failsafe) keeps its own time. Sending by whichever clock says so first feeds it either way;
    an extra keep-alive only repeats the last command.
    """

    def __init__(self, period: float, clock: Callable[[], float], wall: Callable[[], float] = time.monotonic):
        self.period = period
        self._clock = clock
        self._wall = wall
        self._next = self._next_wall = -math.inf

    def due(self) -> bool:
        return self._clock() >= self._next or self._wall() >= self._next_wall

    def done(self) -> None:
        """It was sent now: the next one is due a period later on both clocks."""
        self._next = self._clock() + self.period
        self._next_wall = self._wall() + self.period


class Driver(ABC):
    """Base of every driver. Subclasses never clamp, never time out, never forget the final zero."""

    name = "base"
    has_imu = False  # True: read() pairs each odometry sample with the gyro rate of the same step
    answers_steps = False  # True: its commands carry the lock-step step number to the world (``sim``)
    provides_scan = False  # True: ``read_scan()`` gives the robot's own lidar (a bridged ROS 2 robot)
    config_class: type | None = None  # the dataclass of its settings (the scenario's ``<driver>:`` block)

    def __init__(self, robot_id: int, limits: DriverLimits, clock=time.monotonic):
        self.robot_id = robot_id
        self.limits = limits
        self._clock = clock
        self._lock = threading.RLock()
        self._last_cmd_time: float | None = None
        self._last_sent: tuple[float, float] = (0.0, 0.0)
        self._is_open = False
        self._watchdog: threading.Thread | None = None
        self._stop = threading.Event()
        self.watchdog_trips = 0
        self.fault: str | None = None

    def _configure(self, config, params: dict):
        """``config`` (or ``config_class``'s defaults) with the scenario's settings ``params`` over it;
        an unknown setting is a one-line error naming it."""
        cls = self.config_class
        config = config or cls()
        unknown = set(params) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"{self.name} driver: unknown settings {', '.join(sorted(unknown))}")
        return replace(config, **params) if params else config

    # --- lifecycle -------------------------------------------------------------------
    def open(self) -> "Driver":
        with self._lock:
            if self._is_open:
                return self
            self._open()
            self._is_open = True
            self._stop.clear()
            self._last_cmd_time = None
            self._watchdog = threading.Thread(target=self._watch, name=f"{self.name}-watchdog-{self.robot_id}", daemon=True)
            self._watchdog.start()
        return self

    def close(self) -> None:
        """Zero velocity first, then release the device. Safe to call twice."""
        with self._lock:
            if not self._is_open:
                return
            try:
                self._send(0.0, 0.0)
                self._last_sent = (0.0, 0.0)
            except Exception as e:  # the device may be gone; closing must still finish
                log.warning("%s driver %s: zero command on close failed: %s", self.name, self.robot_id, e)
            self._stop.set()
            self._is_open = False
            try:
                self._close()
            finally:
                if self._watchdog is not None and self._watchdog is not threading.current_thread():
                    self._watchdog.join(timeout=1.0)

    def __enter__(self) -> "Driver":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- commands --------------------------------------------------------------------
    def clamp(self, v: float, w: float) -> tuple[float, float]:
        """Bai 2022 eq. (2): |v| <= v_max, |w| <= w_max; NaN/inf become zero."""
        if not (math.isfinite(v) and math.isfinite(w)):
            return 0.0, 0.0
        lim = self.limits
        return max(-lim.v_max, min(lim.v_max, v)), max(-lim.w_max, min(lim.w_max, w))

    def command(self, v: float, w: float, step: int = -1) -> tuple[float, float]:
        """Send one velocity command (clamped); returns what was sent. A faulted driver sends zero."""
        if not self._is_open:
            raise DriverError(f"{self.name} driver {self.robot_id}: command on a closed driver")
        v, w = self.clamp(float(v), float(w))
        self._check_health()  # on the control step too: a busy supervisor thread must not delay a fault
        if self.fault is not None:
            v, w = 0.0, 0.0
        with self._lock:
            self._send_step(v, w, step)
            self._last_sent = (v, w)
            self._last_cmd_time = self._clock()
        return v, w

    def stop(self) -> None:
        """Zero velocity now (the agent's safe stop)."""
        if self._is_open:
            with self._lock:
                self._send(0.0, 0.0)
                self._last_sent = (0.0, 0.0)

    def read(self) -> Odometry | None:
        """The newest odometry, or None before the first sample."""
        return self._read()

    def read_scan(self):
        """The robot's newest lidar scan as its own wire carries it (``LaserScanData``: stamp, angle_min,
        angle_increment, range_max, ranges), where the driver has one; None otherwise."""
        return None

    def position_fix(self) -> tuple[float, float, float, float] | None:
        """The device's own absolute position estimate ``(x, y, std, stamp)`` in the world frame, where
        it has one (a rover's autopilot); None otherwise. The agent's estimator takes each new one."""
        return None

    @property
    def last_sent(self) -> tuple[float, float]:
        return self._last_sent

    # --- watchdog --------------------------------------------------------------------
    def _watch(self) -> None:
        period = min(0.05, self.limits.cmd_timeout / 4)
        while not self._stop.wait(period):
            with self._lock:
                t = self._last_cmd_time
                if t is None or self._last_sent == (0.0, 0.0):
                    continue
                if self._clock() - t > self.limits.cmd_timeout:
                    log.warning("%s driver %s: no command for %.2f s: zero velocity", self.name, self.robot_id, self.limits.cmd_timeout)
                    self.watchdog_trips += 1
                    try:
                        self._send(0.0, 0.0)
                    except Exception as e:
                        log.error("%s driver %s: watchdog zero failed: %s", self.name, self.robot_id, e)
                    self._last_sent = (0.0, 0.0)

    # --- backend hooks ---------------------------------------------------------------
    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _send(self, v: float, w: float) -> None: ...

    def _check_health(self) -> None:
        """Trip a fault now if the device has gone stale on the driver's clock (a missing heartbeat or
        odometry). ``command()`` calls it every control step, the backend's supervisor thread between
        steps; a backend with nothing to watch keeps this no-op."""

    def _send_step(self, v: float, w: float, step: int) -> None:
        """Send a command belonging to control step ``step`` (lock-step worlds care; devices do not)."""
        self._send(v, w)

    @abstractmethod
    def _read(self) -> Odometry | None: ...

    @abstractmethod
    def _close(self) -> None: ...
