"""The driver interface ``open / command(v, w) / read / close`` and the supervision every device needs.

Like python-can's ``BusABC``: the public methods keep the rules and a backend implements only
the underscored hooks::

    class MyDriver(Driver):
        def _open(self): ...          # connect; return when the device is ready (or raise DriverError)
        def _send(self, v, w): ...    # put one (already clamped) command on the wire
        def _read(self): ...          # the newest Odometry or None
        def _close(self): ...         # release the device (zero velocity was already sent)
        # where the device needs them:
        def _keepalives(self): ...    # [Keepalive(...)]: what the supervisor resends, how often
        def _health(self, now): ...   # a one-line fault reason when the device looks dead, else None
        def _poll(self, timeout): ... # pump a connection for up to ``timeout`` s (default: wait)
        def _fault_stop(self): ...    # what a fault puts on the wire (default: zero velocity)

The rules live here once: clamping to the robot's limits (eq. (2) of Bai 2022); one supervise
thread per driver that runs the command watchdog, the keep-alives and the health check
(``supervise_once``, which tests call directly with a fake clock); the fault latch (the first
reason is kept, zero is sent once, motion is refused until the driver is closed and opened
again); liveness (``liveness()``: seconds since each stream's last sign of life, on the
driver's clock) and ``counters`` (``count(name)``); zero velocity before closing.

Two clocks, both injectable: ``clock`` is the driver's (the agent's: sim time in lock-step,
monotonic in real time) and times the watchdog, the health check and liveness; ``wall`` is
the wall clock, which keep-alives also follow (``Periodic``).

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
    """What every driver enforces, whatever its backend: speeds clipped to ``v_max`` / ``w_max`` and a command
    older than ``cmd_timeout`` replaced by zero (the watchdog, in ``Driver.command``)."""

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

    def __init__(self, period: float):
        self.period = period
        self._next = self._next_wall = -math.inf

    def due(self, now: float, wall: float) -> bool:
        return now >= self._next or wall >= self._next_wall

    def shift(self, dt: float) -> None:
        """The driver's clock jumped by ``dt`` (``Driver.clock_jumped``): the next one is due as late on it."""
        self._next += dt

    def done(self, now: float, wall: float) -> None:
        """It was sent at ``now`` (driver's clock) / ``wall``: the next one is due a period later on both."""
        self._next = now + self.period
        self._next_wall = wall + self.period


@dataclass(frozen=True)
class Keepalive:
    """Something the device needs at least every ``period``; the supervisor sends it when due (``Periodic``)."""

    name: str
    """What it is, for logs (``command``, ``gcs_heartbeat``)."""
    period: float
    """[s] at least this often."""
    send: Callable[[], None] | None = None
    """Puts it on the wire; None: resend the last command (then every command restarts its period)."""
    faulted: bool = False
    """Also sent after a fault (a controller that must keep hearing zero; a GCS heartbeat)."""
    always: bool = False
    """Sent whenever the supervisor runs: while opening and closing too (a GCS heartbeat the vehicle's
    failsafe listens for during the handshake)."""


class Counted:
    """Named counters under ``self._books`` (a lock), shared by drivers and sensor sources: each has
    ``counters``, ``name`` and ``_on_malformed``."""

    def count(self, name: str, malformed: bool = False) -> None:
        """``counters[name] += 1``; a malformed one is also told to ``on_malformed`` as ``<name>/<counter>``."""
        with self._books:
            self.counters[name] = self.counters.get(name, 0) + 1
        if malformed:
            self._on_malformed(f"{self.name}/{name}")


class Driver(Counted, ABC):
    """Base of every driver. Subclasses never clamp, never time out, never forget the final zero."""

    name = "base"
    has_imu = False  # True: read() pairs each odometry sample with the gyro rate of the same step
    answers_steps = False  # True: its commands carry the lock-step step number to the world (``sim``)
    provides_scan = False  # True: ``read_scan()`` gives the robot's own lidar (a bridged ROS 2 robot)
    config_class: type | None = None  # the dataclass of its settings (the scenario's ``<driver>:`` block)
    fault_action = "zero velocity sent"  # what a fault put on the wire, for the log
    supervise_period = 0.05  # [s] the longest wait between supervision rounds (a device to watch: shorter)

    def __init__(self, robot_id: int, limits: DriverLimits, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.monotonic, on_malformed: Callable[[str], None] | None = None):
        self.robot_id = robot_id
        self.limits = limits
        self._clock = clock
        self._wall = wall
        self._on_malformed = on_malformed or (lambda key: None)
        self._lock = threading.RLock()  # the command path: commands, keep-alives, watchdog zeros and trips in order
        self._life = threading.Lock()  # open / close
        self._books = threading.Lock()  # counters and liveness
        self._last_cmd_time: float | None = None
        self._last_sent: tuple[float, float] = (0.0, 0.0)
        self._is_open = False
        self._supervising = False  # open and armed: watchdog, health and keep-alives run, faults trip
        self._feeds: list[tuple[Keepalive, Periodic]] = []
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()  # set: the supervisor (and a backend's waits) stop
        self._seen: dict[str, float] = {}  # stream -> driver clock at its last sign of life
        self.counters: dict[str, int] = {}
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
        """Open the device (``_open``), start the supervisor and arm it. A fault is cleared here only."""
        with self._life:
            if self._is_open:
                return self
            self.fault = None
            self._supervising = False
            with self._books:
                self._seen.clear()
            self._feeds = [(k, Periodic(k.period)) for k in self._keepalives()]
            self._halt.clear()
            try:
                self._open()
                self._start_supervisor()
            except BaseException:
                self._stop_supervisor()
                raise
            with self._lock:
                self._is_open = self._supervising = True
                self._last_cmd_time = None
                self._last_sent = (0.0, 0.0)
                self._first_keepalive()
        return self

    def _first_keepalive(self) -> None:
        """Armed: a driver that keeps its command alive sends zero at once, not a period later (a device
        watchdog that started with closed loop or arming is fed now, however busy this process is)."""
        if not any(k.send is None for k, _ in self._feeds):
            return
        try:
            self._put(0.0, 0.0)
        except Exception as e:  # the keep-alive retries it, and a backend may trip on that
            log.warning("%s driver %s: zero command on opening failed: %s", self.name, self.robot_id, e)

    def close(self) -> None:
        """Zero velocity first, then release the device. Safe to call twice."""
        with self._life:
            if not self._is_open:
                return
            with self._lock:
                self._is_open = self._supervising = False
                try:
                    self._put(0.0, 0.0)
                except Exception as e:  # the device may be gone; closing must still finish
                    log.warning("%s driver %s: zero command on close failed: %s", self.name, self.robot_id, e)
            try:
                self._close()
            finally:
                self._stop_supervisor()

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
            raise self._closed()
        v, w = self.clamp(float(v), float(w))
        self._check_health(self._clock())  # on the control step too: a busy supervisor must not delay a fault
        with self._lock:
            if not self._is_open:
                raise self._closed()
            sent = self._put(v, w, step)
            self._last_cmd_time = self._clock()
        return sent

    def stop(self) -> None:
        """Zero velocity now (the agent's safe stop)."""
        if self._is_open:
            with self._lock:
                self._put(0.0, 0.0)

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

    def _closed(self) -> DriverError:
        return DriverError(f"{self.name} driver {self.robot_id}: command on a closed driver")

    def _put(self, v: float, w: float, step: int = -1) -> tuple[float, float]:
        """Every command reaches the wire here (caller holds ``_lock``): zero once faulted; it restarts
        the period of the keep-alive that resends it."""
        if self.fault is not None:
            v, w = 0.0, 0.0
        self._send_step(v, w, step)
        self._last_sent = (v, w)
        self._commanded(self._clock(), self._wall())
        return v, w

    def _commanded(self, now: float, wall: float) -> None:
        for k, p in self._feeds:
            if k.send is None:
                p.done(now, wall)

    # --- the fault latch ---------------------------------------------------------------
    def _trip(self, reason: str) -> bool:
        """First fault wins: keep ``reason``, put ``_fault_stop`` on the wire once, refuse motion until
        close/open. False when it did not trip (already faulted, or not armed)."""
        with self._lock:
            if self.fault is not None or not self._supervising:
                return False
            self.fault = reason
            log.error("%s driver %s: fault: %s: %s", self.name, self.robot_id, reason, self.fault_action)
            try:
                self._fault_stop()
            except Exception as e:  # the link itself may be what failed
                log.error("%s driver %s: zero on fault failed: %s", self.name, self.robot_id, e)
            self._last_sent = (0.0, 0.0)
        return True

    def _check_health(self, now: float) -> None:
        if self._supervising and self.fault is None:
            reason = self._health(now)
            if reason:
                self._trip(reason)

    def clock_jumped(self, dt: float) -> None:
        """The driver's clock jumped ahead by ``dt`` (a lock-step agent opened its driver at 0 and learns the
        world's time at its first step): every sign of life, the last command and the keep-alives move with it,
        so what the device said while opening is as old as it was, not ``dt`` older."""
        with self._books:
            self._seen = {s: t + dt for s, t in self._seen.items()}
        with self._lock:
            if self._last_cmd_time is not None:
                self._last_cmd_time += dt
            for _, p in self._feeds:
                p.shift(dt)

    # --- counters and liveness ---------------------------------------------------------

    @property
    def wire_sent(self) -> int:
        """Messages this driver has put on its device's wire (every frame, datagram or sample: each backend counts
        ``tx`` once one is on the wire). A lock-step world waits until the device has handled as many as the
        driver had sent when it answered a step (``stack.comm.lockstep.DeviceWires``)."""
        with self._books:
            return self.counters.get("tx", 0)

    @property
    def watchdog_trips(self) -> int:
        return self.counters.get("watchdog_trips", 0)

    def _alive(self, stream: str, now: float | None = None) -> None:
        """A sign of life on ``stream`` (a heartbeat, an odometry sample), at ``now`` on the driver's clock."""
        with self._books:
            self._seen[stream] = self._clock() if now is None else now

    def age(self, stream: str, now: float | None = None) -> float | None:
        """Seconds on the driver's clock since ``stream``'s last sign of life; None before the first."""
        with self._books:
            seen = self._seen.get(stream)
        return None if seen is None else (self._clock() if now is None else now) - seen

    def liveness(self, now: float | None = None) -> dict[str, float]:
        """Every stream seen since opening -> its age [s] on the driver's clock."""
        now = self._clock() if now is None else now
        with self._books:
            return {s: now - t for s, t in self._seen.items()}

    # --- the supervisor ------------------------------------------------------------------
    def supervise_once(self, now: float | None = None, wall: float | None = None) -> None:
        """One round of supervision at ``now`` (driver's clock) and ``wall``: the command watchdog, the
        health check, the keep-alives that are due. The supervise thread calls it in a loop."""
        now = self._clock() if now is None else now
        wall = self._wall() if wall is None else wall
        self._watchdog(now)
        self._check_health(now)
        self._feed(now, wall)

    def _watchdog(self, now: float) -> None:
        with self._lock:
            t = self._last_cmd_time
            if not self._supervising or t is None or self._last_sent == (0.0, 0.0):
                return
            if now - t > self.limits.cmd_timeout:
                log.warning("%s driver %s: no command for %.2f s: zero velocity", self.name, self.robot_id,
                            self.limits.cmd_timeout)
                self.count("watchdog_trips")
                try:
                    self._put(0.0, 0.0)
                except Exception as e:
                    log.error("%s driver %s: watchdog zero failed: %s", self.name, self.robot_id, e)
                    self._last_sent = (0.0, 0.0)

    def _feed(self, now: float, wall: float) -> None:
        for k, p in self._feeds:
            reason = None
            with self._lock:
                if not (k.always or (self._supervising and (self.fault is None or k.faulted))):
                    continue
                if not p.due(now, wall):
                    continue
                p.done(now, wall)
                try:
                    if k.send is None:
                        self._put(*self._last_sent)
                    else:
                        k.send()
                except Exception as e:
                    self.count("tx_error")
                    reason = self._keepalive_failed(k, e)
            if reason:
                self._trip(reason)

    def _supervise(self) -> None:
        period = min([self.supervise_period, self.limits.cmd_timeout / 4] + [k.period / 2 for k, _ in self._feeds])
        while not self._halt.is_set():
            try:
                self.supervise_once()
            except Exception:  # a backend's bug must not end supervision
                log.exception("%s driver %s: supervision failed", self.name, self.robot_id)
            self._poll(period)

    def _start_supervisor(self) -> None:
        """Start the supervise thread (``open`` does; a backend whose handshake needs its keep-alives or its
        ``_poll`` starts it early, from ``_open``)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._supervise, name=f"{self.name}-supervisor-{self.robot_id}",
                                            daemon=True)
            self._thread.start()

    def _stop_supervisor(self) -> None:
        self._halt.set()
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=1.0)

    # --- backend hooks ---------------------------------------------------------------
    @abstractmethod
    def _open(self) -> None:
        """Backend: connect to the device; return when it is ready, or raise ``DriverError`` saying why not."""

    @abstractmethod
    def _send(self, v: float, w: float) -> None:
        """Backend: put one command on the wire; ``(v, w)`` are already clipped and watched by ``command``."""

    def _send_step(self, v: float, w: float, step: int) -> None:
        """Send a command belonging to control step ``step`` (lock-step worlds care; devices do not)."""
        self._send(v, w)

    @abstractmethod
    def _read(self) -> Odometry | None:
        """Backend: the newest ``Odometry`` the device sent since the last call, or None if nothing new came."""

    @abstractmethod
    def _close(self) -> None:
        """Backend: release the device (``close`` has already sent zero velocity)."""

    def _keepalives(self) -> list[Keepalive]:
        """What the device needs resent, built when opening. Default: nothing."""
        return []

    def _health(self, now: float) -> str | None:
        """A one-line fault reason if the device has gone stale at ``now`` on the driver's clock (a missing
        heartbeat, odometry: see ``age``), else None. Called every control step and every supervision round."""
        return None

    def _poll(self, timeout: float) -> None:
        """Between supervision rounds: wait ``timeout`` s, or pump the connection for up to that long."""
        self._halt.wait(timeout)

    def _fault_stop(self) -> None:
        """What a fault puts on the wire, once (the fault is already set). Default: zero velocity."""
        self._send(0.0, 0.0)

    def _keepalive_failed(self, keepalive: Keepalive, error: Exception) -> str | None:
        """A keep-alive could not be sent (counted as ``tx_error``): a fault reason, or None to log it only."""
        log.error("%s driver %s: %s keep-alive failed: %s", self.name, self.robot_id, keepalive.name, error)
        return None
