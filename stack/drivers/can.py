"""``can``: a differential drive on two ODrive axes (CANSimple, firmware 0.6.x), over python-can.

The left and right wheel each have an ODrive axis with its own node id. Opening clears the
axes' errors, puts them in velocity control and closed loop, and waits until both
heartbeats say so. A command becomes one ``Set_Input_Vel`` per axis (wheel kinematics with
radius, track, gear and the direction of each wheel), resent every ``keepalive_period`` so
the axes' watchdogs stay fed. A python-can ``Notifier`` decodes the axes' heartbeats and
encoder estimates; ``read()`` returns the body speeds of the newest pair of estimates.
Supervision (the keepalive, the heartbeat timeout, the fault latch, ``counters`` and
``liveness()``: ``heartbeat_left``, ``heartbeat_right``, ``odom``) is the base class's.

A fault (a heartbeat missing for ``heartbeat_timeout``, an axis error, an axis leaving
closed loop, a bus error) sends zero velocity and ``Estop`` to both axes and sets
``fault`` to a one-line reason with the decoded error; the base class then sends no
motion, and the driver stays faulted until it is closed and opened again.

>>> cfg = CanConfig(interface="slcan", channel="/dev/ttyACM0", node_left=0, node_right=1)
>>> drv = CanDriver(1, DriverLimits(1.0, 2.0), cfg)            # doctest: +SKIP
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import can

from . import odrive
from .base import Driver, DriverError, DriverLimits, Keepalive, Odometry

log = logging.getLogger(__name__)

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class CanConfig:
    """Where the two ODrive axes are and what wheels they turn (defaults: a Clearpath Jackal's wheels)."""

    interface: str = "socketcan"
    """python-can interface name: ``socketcan`` on a robot, ``slcan`` for a USB-CAN adapter
    (or the simulated one on a pseudo-terminal), ``virtual`` for in-process tests."""
    channel: str = "can0"
    """python-can channel: ``can0``, a serial device such as ``/dev/ttyACM0``, a virtual bus name."""
    bitrate: int = 500_000
    """[bit/s] CAN bitrate, given to interfaces that set it (``slcan``); socketcan takes it from ``ip link``."""
    node_left: int = 0
    """CANSimple node id (0..62; 63 is the unaddressed id) of the left wheel's axis."""
    node_right: int = 1
    """CANSimple node id (0..62; 63 is the unaddressed id) of the right wheel's axis."""
    wheel_radius: float = 0.098
    """[m] wheel radius."""
    track_width: float = 0.37559
    """[m] distance between the left and right wheel contact points."""
    gear_ratio: float = 1.0
    """motor turns per wheel turn (the ODrive measures the motor)."""
    direction_left: int = 1
    """+1 if a positive motor velocity turns the left wheel forward, else -1."""
    direction_right: int = -1
    """+1 if a positive motor velocity turns the right wheel forward, else -1 (mirrored motor: usual)."""
    heartbeat_timeout: float = 0.3
    """[s] a heartbeat older than this is a fault: 3 periods of the ODrive's default 100 ms."""
    open_timeout: float = 1.0
    """[s] how long opening waits for both axes to report CLOSED_LOOP_CONTROL without error."""
    keepalive_period: float = 0.1
    """[s] the last command is resent this often, feeding the axes' watchdogs (the vendor resends within 0.5 s)."""
    input_mode: str = "VEL_RAMP"
    """ODrive input mode for velocity control: ``VEL_RAMP`` (the axis ramps at its vel_ramp_rate) or ``PASSTHROUGH``."""
    can_log: str | None = None
    """Path of a python-can log of every frame sent and received (``.asc``, ``.blf``, ``.log``, ``.csv``...); None: no log."""
    bus_options: Mapping[str, Any] = field(default_factory=dict)
    """Further keyword arguments of ``can.Bus`` (e.g. ``{"sleep_after_open": 0}`` for slcan adapters that need no settling)."""

    def __post_init__(self):
        for n in (self.node_left, self.node_right):
            if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= odrive.MAX_AXIS_NODE_ID:
                raise ValueError(f"can driver: node id {n!r} out of range 0..{odrive.MAX_AXIS_NODE_ID} "
                                 f"({odrive.UNADDRESSED_NODE_ID} is CANSimple's unaddressed id)")
        if self.node_left == self.node_right:
            raise ValueError(f"can driver: both wheels on node {self.node_left}")
        if self.direction_left not in (1, -1) or self.direction_right not in (1, -1):
            raise ValueError("can driver: wheel directions must be +1 or -1")
        for name in ("wheel_radius", "track_width", "gear_ratio", "heartbeat_timeout", "open_timeout",
                     "keepalive_period", "bitrate"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"can driver: {name} must be a positive number, not {value!r}")
        if self.input_mode not in ("VEL_RAMP", "PASSTHROUGH"):
            raise ValueError(f"can driver: input_mode must be VEL_RAMP or PASSTHROUGH, not {self.input_mode!r}")

    # --- differential-drive kinematics (motor side in rev/s, as the ODrive counts) ----
    def motor_velocities(self, v: float, w: float) -> tuple[float, float]:
        """Body (v [m/s], w [rad/s]) -> (left, right) motor velocity [rev/s]."""
        half = 0.5 * w * self.track_width
        k = self.gear_ratio / (TWO_PI * self.wheel_radius)
        return (v - half) * k * self.direction_left, (v + half) * k * self.direction_right

    def body_velocity(self, left: float, right: float) -> tuple[float, float]:
        """(left, right) motor velocity [rev/s] -> body (v [m/s], w [rad/s])."""
        k = TWO_PI * self.wheel_radius / self.gear_ratio
        vl, vr = left * self.direction_left * k, right * self.direction_right * k
        return 0.5 * (vl + vr), (vr - vl) / self.track_width


class _Axis:
    """What the driver knows of one ODrive axis (guarded by the driver's state lock)."""

    def __init__(self, side: str, node_id: int):
        self.side = side
        self.node_id = node_id
        self.label = f"{side} axis (node {node_id})"
        self.stream = f"heartbeat_{side}"  # its liveness stream
        self.reset()

    def reset(self) -> None:
        self.heartbeats = 0
        self.error = 0
        self.state = odrive.AxisState.UNDEFINED
        self.active_errors: int | None = None  # Get_Error reply, when one came
        self.disarm_reason: int | None = None
        self.vel: float | None = None  # [rev/s] newest encoder estimate
        self.fresh = False  # an estimate since the last odometry sample

    def status(self) -> str:
        return f"state {odrive.state_name(self.state)}, error {odrive.error_text(self.error)}"


class _Receiver(can.Listener):
    """The Notifier's listener: hands frames and bus errors to the driver."""

    def __init__(self, driver: "CanDriver"):
        self._driver = driver

    def on_message_received(self, msg: can.Message) -> None:
        self._driver._on_frame(msg)

    def on_error(self, exc: Exception) -> None:
        self._driver._on_bus_error(exc)


class CanDriver(Driver):
    """Two ODrive axes (left, right wheel) on one CAN bus.

    ``bus``: an already-made ``can.BusABC`` to use instead of opening ``config``'s interface
    (tests: a ``virtual`` bus); it stays the caller's, who shuts it down. ``clock`` times the
    command watchdog and the heartbeat timeout (the agent's clock: wall time, or sim time in
    lock-step); the keepalive follows it or ``wall``, whichever is first; ``stamp`` stamps the
    odometry. ``**params`` are CanConfig fields (the scenario's driver settings) that override
    ``config``. ``session``, ``keys`` and ``on_malformed``/``on_odom`` are the agent's common
    driver arguments: the first two are not used, ``on_malformed`` is told ``can/<counter>``
    for each malformed frame and ``on_odom`` gets each new odometry sample.
    """

    name = "can"
    config_class = CanConfig
    fault_action = "zero velocity and Estop sent"

    def __init__(self, robot_id: int, limits: DriverLimits, config: CanConfig | None = None, *,
                 bus: can.BusABC | None = None, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.monotonic, stamp: Callable[[], float] = time.time,
                 on_odom: Callable[[Odometry], None] | None = None, on_malformed: Callable[[str], None] | None = None,
                 session: Any = None, keys: Any = None, **params):
        super().__init__(robot_id, limits, clock, wall, on_malformed)
        self.config = self._configure(config, params)
        self._given_bus = bus
        self._stamp = stamp
        self._on_odom = on_odom
        self.left = _Axis("left", self.config.node_left)
        self.right = _Axis("right", self.config.node_right)
        self._axes = {a.node_id: a for a in (self.left, self.right)}
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._logger: can.Listener | None = None
        self._state = threading.Condition()  # guards the axes and _latest
        self._tx_lock = threading.Lock()  # one sender at a time: bus and log
        self._latest: Odometry | None = None

    # --- lifecycle --------------------------------------------------------------------
    def _open(self) -> None:
        cfg = self.config
        with self._state:
            for a in self._axes.values():
                a.reset()
            self._latest = None
        try:
            self._bus = self._given_bus or can.Bus(interface=cfg.interface, channel=cfg.channel, bitrate=cfg.bitrate,
                                                   **dict(cfg.bus_options))
        except (can.CanError, OSError, ValueError, ImportError) as e:
            raise DriverError(f"can driver {self.robot_id}: cannot open {cfg.interface} {cfg.channel}: {e}") from e
        try:
            if cfg.can_log:
                try:
                    self._logger = can.Logger(cfg.can_log)
                except (OSError, ValueError) as e:
                    raise DriverError(f"can driver {self.robot_id}: cannot write the CAN log {cfg.can_log}: {e}") from e
            self._notifier = can.Notifier(self._bus, [_Receiver(self)], timeout=0.05)
            self._start_axes()
        except (can.CanError, OSError) as e:  # the adapter itself failed (unplugged, its far end gone)
            where = self._bus_name()
            self._teardown()
            raise DriverError(f"can driver {self.robot_id}: cannot start the axes on {where}: {e}") from e
        except BaseException:
            self._teardown()
            raise

    def _start_axes(self) -> None:
        """Clear errors, velocity mode, closed loop; wait until both heartbeats confirm it."""
        cfg = self.config
        with self._state:
            seen = {n: a.heartbeats for n, a in self._axes.items()}
        mode = odrive.InputMode[cfg.input_mode]
        for node in self._axes:
            self._tx(odrive.encode("Clear_Errors", node, Identify=0))
            self._tx(odrive.encode("Set_Controller_Mode", node, Control_Mode=odrive.ControlMode.VELOCITY_CONTROL,
                                   Input_Mode=mode))
            self._tx(odrive.encode("Set_Axis_State", node, Axis_Requested_State=odrive.AxisState.CLOSED_LOOP_CONTROL))

        def ready(a: _Axis) -> bool:
            return a.heartbeats > seen[a.node_id] and a.state == odrive.AxisState.CLOSED_LOOP_CONTROL and a.error == 0

        with self._state:
            if not self._wait_fed(lambda: all(ready(a) for a in self._axes.values()), cfg.open_timeout):
                why = "; ".join(f"{a.label}: " + (a.status() if a.heartbeats > seen[a.node_id] else "no heartbeat")
                                for a in self._axes.values() if not ready(a))
                raise DriverError(f"can driver {self.robot_id}: axes not in CLOSED_LOOP_CONTROL after "
                                  f"{cfg.open_timeout:g} s on {self._bus_name()}: {why}")
            now = self._clock()
            for a in self._axes.values():  # the heartbeat timeout counts from here
                self._alive(a.stream, now)

    def _wait_fed(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Wait (holding ``_state``) until ``pred``; every ``keepalive_period`` meanwhile a Get_Error request to each
        axis feeds its watchdog, armed since Set_Axis_State (a slow confirmation must not trip it: the keep-alive
        starts only once the driver is open), and its reply says what an axis that stays out of closed loop has."""
        deadline = time.monotonic() + timeout
        while not self._state.wait_for(pred, min(self.config.keepalive_period, max(0.0, deadline - time.monotonic()))):
            if time.monotonic() >= deadline:
                return False
            for node in self._axes:
                self._tx(odrive.request("Get_Error", node))
        return True

    def _close(self) -> None:
        self._stop_supervisor()
        try:
            for node in self._axes:
                self._tx(odrive.encode("Set_Axis_State", node, Axis_Requested_State=odrive.AxisState.IDLE))
        except (can.CanError, OSError) as e:
            log.warning("can driver %s: IDLE on close failed: %s", self.robot_id, e)
        self._teardown()

    def _teardown(self) -> None:
        """Stop the notifier and the log; shut the bus down if this driver made it."""
        if self._notifier is not None:
            self._notifier.stop(timeout=1.0)
            self._notifier = None
        with self._tx_lock:
            if self._logger is not None:
                self._logger.stop()
                self._logger = None
        if self._bus is not None and self._bus is not self._given_bus:
            self._bus.shutdown()
        self._bus = None

    # --- commands ---------------------------------------------------------------------
    def _send(self, v: float, w: float) -> None:
        """One Set_Input_Vel per axis. A faulted driver sends nothing: the axes are in Estop."""
        if self.fault is not None:
            return
        try:
            for axis, vel in zip((self.left, self.right), self.config.motor_velocities(v, w)):
                self._tx(odrive.encode("Set_Input_Vel", axis.node_id, Input_Vel=vel, Input_Torque_FF=0.0))
        except (can.CanError, OSError) as e:
            raise DriverError(f"can driver {self.robot_id}: send failed on {self._bus_name()}: {e}") from e

    def _tx(self, msg: can.Message) -> None:
        with self._tx_lock:
            if self._bus is None:
                raise can.CanOperationError("bus is closed")
            msg.timestamp = time.time()
            msg.is_rx = False
            self._bus.send(msg)
            if self._logger is not None:
                self._logger(msg)
        self.count("tx")

    # --- receiving (Notifier thread) --------------------------------------------------
    def _on_frame(self, msg: can.Message) -> None:
        """Decode one frame; anything unexpected is counted, nothing raises."""
        if self._logger is not None:
            with self._tx_lock:
                if self._logger is not None:
                    self._logger(msg)
        try:
            f = odrive.decode(msg, self._axes)
        except odrive.ProtocolError as e:
            return self.count(e.kind, malformed=True)
        axis = self._axes[f.node_id]
        if f.remote:  # requests come from hosts; another host on our axes
            return self.count("unexpected", malformed=True)
        if f.name == "Heartbeat":
            self._on_heartbeat(axis, f.signals)
        elif f.name == "Get_Encoder_Estimates":
            self._on_encoder(axis, f.signals)
        elif f.name == "Get_Error":
            with self._state:
                axis.active_errors, axis.disarm_reason = f.signals["Active_Errors"], f.signals["Disarm_Reason"]
        else:  # a command to our axes from someone else, or a reply we do not use
            self.count("unexpected", malformed=True)

    def _on_heartbeat(self, axis: _Axis, s: dict) -> None:
        with self._state:
            axis.heartbeats += 1
            self._alive(axis.stream)
            axis.error, axis.state = int(s["Axis_Error"]), int(s["Axis_State"])
            self.count("heartbeat")
            self._state.notify_all()
        if not self._supervising:
            return
        if axis.error:
            self._trip(f"{axis.label}: axis error {odrive.error_text(axis.error)} "
                       f"(state {odrive.state_name(axis.state)})")
        elif axis.state != odrive.AxisState.CLOSED_LOOP_CONTROL:
            self._trip(f"{axis.label}: left CLOSED_LOOP_CONTROL, now {odrive.state_name(axis.state)}")

    def _on_encoder(self, axis: _Axis, s: dict) -> None:
        vel = s["Vel_Estimate"]
        if not math.isfinite(vel):
            return self.count("bad_value", malformed=True)
        with self._state:
            axis.vel, axis.fresh = vel, True
            self.count("encoder")
            if not (self.left.fresh and self.right.fresh):
                return
            self.left.fresh = self.right.fresh = False
            v, w = self.config.body_velocity(self.left.vel, self.right.vel)
            odo = self._latest = Odometry(v=v, w=w, stamp=self._stamp())
        self._alive("odom")
        if self._on_odom is not None:
            self._on_odom(odo)

    def _on_bus_error(self, exc: Exception) -> None:
        self.count("bus_error")
        self._trip(f"CAN bus error on {self._bus_name()}: {exc}")
        self._halt.wait(0.1)  # the Notifier retries at once: do not spin on a dead bus

    def _read(self) -> Odometry | None:
        with self._state:
            return self._latest

    # --- supervision hooks (the base's supervisor calls them) --------------------------
    @property
    def supervise_period(self) -> float:
        """A fifth of the heartbeat_timeout (and 20 ms at most) between supervision rounds."""
        return min(0.02, self.config.heartbeat_timeout / 5)

    def _keepalives(self) -> list[Keepalive]:
        """The last command, feeding the axes' watchdogs; none once faulted (the axes are in Estop)."""
        return [Keepalive("command", self.config.keepalive_period)]

    def _health(self, now: float) -> str | None:
        """A heartbeat older than ``heartbeat_timeout`` on the driver's clock is a fault."""
        stale = [(a, age) for a in self._axes.values()
                 if (age := self.age(a.stream, now)) is not None and age > self.config.heartbeat_timeout]
        return "; ".join(f"{a.label}: no heartbeat for {age:.2f} s" for a, age in stale) or None

    def _fault_stop(self) -> None:
        """Zero velocity and Estop to both axes."""
        for node in self._axes:
            try:
                self._tx(odrive.encode("Set_Input_Vel", node, Input_Vel=0.0, Input_Torque_FF=0.0))
                self._tx(odrive.encode("Estop", node))
                self.count("estop")
            except (can.CanError, OSError) as e:  # the bus itself may be what failed
                log.error("can driver %s: Estop to node %d failed: %s", self.robot_id, node, e)

    def _keepalive_failed(self, keepalive: Keepalive, error: Exception) -> str | None:
        return f"keepalive send failed on {self._bus_name()}: {error.__cause__ or error}"

    # --- helpers ----------------------------------------------------------------------
    def _bus_name(self) -> str:
        if self._bus is not None and self._bus is self._given_bus:
            return self._bus.channel_info
        return f"{self.config.interface} {self.config.channel}"


__all__ = ["CanConfig", "CanDriver"]
