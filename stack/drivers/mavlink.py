"""``mavlink``: an ArduPilot Rover in GUIDED mode, over MAVLink 2 (dialect ardupilotmega, pymavlink).

We are a companion computer / GCS on the vehicle's link (UDP, TCP or a serial port). Opening
sends our 1 Hz GCS ``HEARTBEAT`` (the rover's FS_GCS failsafe listens for it), waits for the
vehicle's (``MAV_TYPE_GROUND_ROVER``), switches it to GUIDED (``MAV_CMD_DO_SET_MODE``), asks
for ``LOCAL_POSITION_NED`` and ``ATTITUDE`` (and ``GLOBAL_POSITION_INT`` with a ``datum``) at the
configured rates (``MAV_CMD_SET_MESSAGE_INTERVAL``) and arms it (``MAV_CMD_COMPONENT_ARM_DISARM``),
each step checked by its ``COMMAND_ACK`` and the mode and arming by the vehicle's heartbeat. A refusal
raises ``DriverError`` naming what was refused and the ``MAV_RESULT``.

A command becomes one ``SET_POSITION_TARGET_LOCAL_NED`` in ``MAV_FRAME_BODY_NED`` with type
mask 1511 (forward velocity + yaw rate): ``vx = v``, ``yaw_rate = -w`` (NED turns clockwise,
our ``w`` counter-clockwise); the last one is resent every ``keepalive_period`` (the rover
stops 3 s after its last target). ``read()`` turns the newest ``LOCAL_POSITION_NED`` +
``ATTITUDE`` pair into body speeds and the vehicle's pose; ``position_fix()`` gives the vehicle's own position
estimate, for the agent's estimator.

Frames of position. ArduPilot's ``LOCAL_POSITION_NED`` is relative to the vehicle's own EKF
origin, which each vehicle sets for itself (at its first GPS fix, or by
``SET_GPS_GLOBAL_ORIGIN``): it is the device's odometry frame, and ``read().pose`` stays in
it (the agent maps it into the site frame). With a ``datum`` (the scenario's ``site.datum``:
the site frame's origin on WGS 84) ``position_fix()`` is the vehicle's ``GLOBAL_POSITION_INT``
on the datum's local tangent plane (``stack.models.geodesy``): the site frame, so rovers
whose EKF origins differ agree on where they are; before the first one (or while the vehicle
has no position: lat = lon = 0, counted ``no_global_fix``) it is None. ``set_ekf_origin`` also
moves the vehicle's EKF origin to the datum on opening (``SET_GPS_GLOBAL_ORIGIN``, confirmed by
its ``GPS_GLOBAL_ORIGIN``; a vehicle that keeps its own origin is a warning, counted
``origin_refused``, as the fixes do not depend on it). Without a datum ``position_fix()`` is
``LOCAL_POSITION_NED``, as it always was: in the site frame only where the EKF origin is the
site origin.

A fault (the vehicle's heartbeat missing for ``heartbeat_timeout``, the vehicle leaving
GUIDED, the vehicle disarmed) sends a zero target and sets ``fault`` to a one-line reason;
the base class then sends no motion. Closing sends a zero target, HOLD and disarm, unless
someone else took the vehicle out of GUIDED (a pilot's MANUAL): we give back only what we hold.

Malformed or foreign traffic (garbage bytes, a bad CRC, unknown message ids, other system
ids) is counted in ``counters`` and ignored; nothing raises. Supervision (our heartbeat, the
keepalive, the vehicle's heartbeat timeout, the fault latch, ``counters``, ``liveness()``:
``heartbeat``, ``local_position``, ``attitude``, ``odom``, with a datum ``global_position``) is the
base class's, and its one thread also receives (``_poll``).

Frames: NED (x north, y east, yaw clockwise from north) <-> our world (x east, y north, yaw
counter-clockwise from east): ``ned_to_world`` / ``world_to_ned``, the only copy of it
(the simulated rover in ``stack.sim_bridge.rover_sim`` uses these).

>>> cfg = MavlinkConfig(connection="udpin:127.0.0.1:14550")
>>> drv = MavlinkDriver(1, DriverLimits(1.0, 2.0), cfg)       # doctest: +SKIP
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from ..models.geodesy import Datum, check_datum, geodetic_to_site
from ..models.geometry import wrap as wrap_angle  # the one angle wrap, (-pi, pi]
from .base import Driver, DriverError, DriverLimits, Keepalive, Odometry

log = logging.getLogger(__name__)

# --- protocol constants (all from the dialect) -----------------------------------------
ROVER_MODES: dict[str, int] = {e.name.removeprefix("ROVER_MODE_"): k
                               for k, e in mav.enums["ROVER_MODE"].items() if not e.name.endswith("ENUM_END")}
"""ArduPilot Rover mode name -> HEARTBEAT custom_mode (MANUAL 0, HOLD 4, GUIDED 15...)."""
MODE_GUIDED = ROVER_MODES["GUIDED"]
MODE_HOLD = ROVER_MODES["HOLD"]

_TM = mav.enums["POSITION_TARGET_TYPEMASK"]
_IGNORE = {e.name.removeprefix("POSITION_TARGET_TYPEMASK_").removesuffix("_IGNORE"): k for k, e in _TM.items()}
TYPE_MASK_VEL_YAW_RATE = (_IGNORE["X"] | _IGNORE["Y"] | _IGNORE["Z"] | _IGNORE["VZ"] | _IGNORE["AX"]
                          | _IGNORE["AY"] | _IGNORE["AZ"] | _IGNORE["YAW"])
"""SET_POSITION_TARGET_LOCAL_NED type_mask using vx, vy and yaw_rate only: 1511 (0x05E7)."""
YAW_RATE_IGNORE = _IGNORE["YAW_RATE"]
VX_IGNORE = _IGNORE["VX"]
POSITION_IGNORE = _IGNORE["X"] | _IGNORE["Y"] | _IGNORE["Z"]

TELEMETRY = {"LOCAL_POSITION_NED": mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, "ATTITUDE": mav.MAVLINK_MSG_ID_ATTITUDE,
             "GLOBAL_POSITION_INT": mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT}

_LINK_PREFIXES = ("udpin:", "udpout:", "udp:", "tcp:", "tcpin:")


def origin_e7(origin: Datum) -> tuple[int, int, int]:
    """(lat, lon, alt) -> GPS_GLOBAL_ORIGIN's fields: degE7, degE7, mm."""
    return round(origin[0] * 1e7), round(origin[1] * 1e7), round(origin[2] * 1e3)


def mode_name(custom_mode: int) -> str:
    """HEARTBEAT custom_mode of a rover -> its name (``HOLD``), or ``mode 42`` for one we do not know."""
    for name, number in ROVER_MODES.items():
        if number == custom_mode:
            return name
    return f"mode {custom_mode}"


def mode_number(name: str) -> int:
    try:
        return ROVER_MODES[name.upper()]
    except KeyError:
        raise ValueError(f"unknown rover mode {name!r} (known: {', '.join(ROVER_MODES)})") from None


def result_name(result: int) -> str:
    """COMMAND_ACK result -> ``MAV_RESULT_DENIED`` etc."""
    entry = mav.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"


def enum_name(enum: str, value: int) -> str:
    entry = mav.enums[enum].get(value)
    return entry.name if entry is not None else f"{enum} {value}"


# --- frames (the one copy of the NED <-> world conversion) --------------------------------
def ned_to_world(north: float, east: float, yaw_ned: float) -> tuple[float, float, float]:
    """NED position and heading -> our world frame (x east, y north, yaw counter-clockwise from east)."""
    return east, north, wrap_angle(math.pi / 2.0 - yaw_ned)


def world_to_ned(x: float, y: float, yaw: float) -> tuple[float, float, float]:
    """Our world pose -> (north, east, yaw_ned). The map is its own inverse."""
    return ned_to_world(x, y, yaw)


def ned_velocity(v: float, yaw_ned: float) -> tuple[float, float]:
    """Forward speed along a NED heading -> (v_north, v_east)."""
    return v * math.cos(yaw_ned), v * math.sin(yaw_ned)


def forward_speed(v_north: float, v_east: float, yaw_ned: float) -> float:
    """NED ground velocity -> its component along the heading (the body's forward speed)."""
    return v_north * math.cos(yaw_ned) + v_east * math.sin(yaw_ned)


def yaw_rate_ned(w: float) -> float:
    """Our yaw rate (counter-clockwise positive) <-> NED yaw rate (clockwise positive); its own inverse."""
    return -w


@dataclass(frozen=True)
class MavlinkConfig:
    """Where the rover's autopilot is and how the driver talks to it (defaults: ArduPilot's)."""

    connection: str = "udpin:127.0.0.1:14550"
    """pymavlink link: ``udpin:HOST:PORT`` (listen: the vehicle or a router sends to us), ``udpout:HOST:PORT``
    (we send first), ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``, or a serial device (``/dev/ttyACM0``, ``COM3``)."""
    baud: int = 115200
    """[bit/s] serial baud rate (serial links only)."""
    source_system: int = 255
    """Our MAVLink system id: the GCS id the rover's FS_GCS failsafe watches (its SYSID_MYGCS, default 255)."""
    source_component: int = 190
    """Our MAVLink component id (190: MAV_COMP_ID_MISSIONPLANNER, a GCS / companion)."""
    target_system: int = 1
    """The vehicle's system id (its SYSID_THISMAV)."""
    target_component: int = 1
    """The autopilot's component id (MAV_COMP_ID_AUTOPILOT1)."""
    heartbeat_period: float = 1.0
    """[s] period of our GCS HEARTBEAT."""
    heartbeat_timeout: float = 3.0
    """[s] a vehicle heartbeat older than this is a fault (3 periods of its 1 Hz)."""
    connect_timeout: float = 5.0
    """[s] how long opening waits for the vehicle's first HEARTBEAT."""
    ack_timeout: float = 1.0
    """[s] how long one COMMAND_LONG waits for its COMMAND_ACK before it is resent."""
    command_retries: int = 2
    """How often a COMMAND_LONG without an ACK is resent (confirmation field counting up); refusals are not retried."""
    mode_timeout: float = 3.0
    """[s] after the ACK, how long opening waits for the vehicle's heartbeat to show GUIDED."""
    arm_timeout: float = 3.0
    """[s] after the ACK, how long opening waits for the heartbeat's armed flag (MAV_MODE_FLAG_SAFETY_ARMED)."""
    keepalive_period: float = 0.25
    """[s] the last target is resent this often (the rover stops 3 s after its last target)."""
    position_rate: float = 10.0
    """[Hz] requested rate of LOCAL_POSITION_NED (forward speed, odometry pose) and, with a datum, of
    GLOBAL_POSITION_INT (position fix)."""
    attitude_rate: float = 10.0
    """[Hz] requested rate of ATTITUDE (heading, yaw rate)."""
    position_std: float = 0.3
    """[m] standard deviation of the vehicle's own position estimate (its EKF's, from its GNSS), for the agent's
    estimator: GLOBAL_POSITION_INT's with a datum, LOCAL_POSITION_NED's without (the same estimate; the 1e-7 deg of
    GLOBAL_POSITION_INT are 1.1 cm, well inside it). 0.3 m: a good GNSS receiver with SBAS; say 0.02 for RTK fixed."""
    datum: tuple[float, float, float] | None = None
    """(lat [deg], lon [deg], alt [m]) of the site frame's origin (the scenario's ``site.datum``): the vehicle is then
    placed by GLOBAL_POSITION_INT (asked for at ``position_rate``) on the datum's WGS 84 tangent plane, x east,
    y north. None: position fixes are LOCAL_POSITION_NED, relative to the vehicle's own EKF origin."""
    set_ekf_origin: bool = False
    """With a datum: set the vehicle's EKF origin to it on opening (SET_GPS_GLOBAL_ORIGIN), so LOCAL_POSITION_NED
    (odometry) is in the site frame too. ArduPilot keeps an origin its EKF already uses: then a warning."""

    def __post_init__(self):
        c = self.connection
        if not (c.startswith(_LINK_PREFIXES) or c.startswith("/dev/") or c.upper().startswith("COM")):
            raise ValueError(f"mavlink driver: connection {c!r} is not a link to one vehicle "
                             f"(use {', '.join(p + '...' for p in _LINK_PREFIXES)} or a serial device)")
        for name in ("source_system", "source_component", "target_system", "target_component"):
            value = getattr(self, name)
            if not (isinstance(value, int) and 1 <= value <= 255):
                raise ValueError(f"mavlink driver: {name} must be 1..255, not {value!r}")
        if not (isinstance(self.command_retries, int) and self.command_retries >= 0):
            raise ValueError(f"mavlink driver: command_retries must be a whole number >= 0, not {self.command_retries!r}")
        for name in ("baud", "heartbeat_period", "heartbeat_timeout", "connect_timeout", "ack_timeout", "mode_timeout",
                     "arm_timeout", "keepalive_period", "position_rate", "attitude_rate", "position_std"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"mavlink driver: {name} must be a positive number, not {value!r}")
        if self.datum is not None:
            try:
                object.__setattr__(self, "datum", check_datum(self.datum))
            except ValueError as e:
                raise ValueError(f"mavlink driver: {e}") from None
        if not isinstance(self.set_ekf_origin, bool):
            raise ValueError(f"mavlink driver: set_ekf_origin must be true or false, not {self.set_ekf_origin!r}")
        if self.set_ekf_origin and self.datum is None:
            raise ValueError("mavlink driver: set_ekf_origin needs a datum (the site's [lat_deg, lon_deg, alt_m])")
        if self.keepalive_period > 1.0:
            raise ValueError("mavlink driver: keepalive_period must be <= 1 s (the rover stops 3 s after its last target)")


class MavlinkDriver(Driver):
    """An ArduPilot Rover driven in GUIDED with body-frame velocity + yaw-rate targets.

    ``clock`` times the vehicle's heartbeat timeout (the agent's clock); our heartbeat and
    the keepalive follow it or ``wall``, whichever is first (the FS_GCS failsafe keeps the
    vehicle's time); ``stamp`` stamps odometry and position fixes. ``**params`` are
    MavlinkConfig fields (the scenario's driver settings) that override ``config``.
    ``session``, ``keys`` and ``on_malformed``/``on_odom`` are the agent's common driver
    arguments: the first two are not used, ``on_malformed`` is told ``mavlink/<counter>`` for
    each malformed or foreign message and ``on_odom`` gets each new odometry sample.
    """

    name = "mavlink"
    config_class = MavlinkConfig
    fault_action = "zero target sent"

    def __init__(self, robot_id: int, limits: DriverLimits, config: MavlinkConfig | None = None, *,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.monotonic,
                 stamp: Callable[[], float] = time.time, on_odom: Callable[[Odometry], None] | None = None,
                 on_malformed: Callable[[str], None] | None = None, session: Any = None, keys: Any = None, **params):
        super().__init__(robot_id, limits, clock, wall, on_malformed)
        self.config = self._configure(config, params)
        self._stamp = stamp
        self._on_odom = on_odom
        self._conn: Any = None  # a pymavlink mavfile: only its transport (recv/write/select) is used
        self._datagrams = False
        self._enc: mav.MAVLink | None = None
        self._parser = self._new_parser()
        self._state = threading.Condition()  # guards vehicle state, telemetry, acks
        self._tx_lock = threading.Lock()  # one sender at a time (the encoder's sequence number)
        self._reset_state()

    def _reset_state(self) -> None:
        self._hb_count = 0
        self._vehicle_type: int | None = None
        self._custom_mode: int | None = None
        self._base_mode = 0
        self._acks: dict[int, Any] = {}
        self._pos: Any = None
        self._att: Any = None
        self._pos_fresh = self._att_fresh = False
        self._latest: Odometry | None = None
        self._fix: tuple[float, float, float, float] | None = None
        self._origin: Datum | None = None  # the vehicle's EKF origin, from its newest GPS_GLOBAL_ORIGIN
        self._taken_over = False  # someone else took the vehicle out of GUIDED (or disarmed it)
        self._boot = time.monotonic()

    # --- lifecycle --------------------------------------------------------------------
    def _open(self) -> None:
        with self._state:
            self._reset_state()
        self._parser = self._new_parser()
        self._connect()
        self._start_supervisor()  # its _poll receives, and our GCS heartbeat runs through the handshake
        moded = False
        try:
            self._wait_heartbeat()
            self._send_heartbeat()  # at once: a udpin link only now knows where the vehicle is
            self._set_mode(MODE_GUIDED, "GUIDED")
            moded = True  # from here on the vehicle is ours to give back
            self._handshake()
        except BaseException:
            if moded:  # leave the vehicle as safe as we can: HOLD and disarmed, without waiting
                self._release(wait=False)
            self._teardown()
            raise

    def _connect(self) -> None:
        cfg = self.config
        try:
            self._conn = mavutil.mavlink_connection(cfg.connection, baud=cfg.baud, source_system=cfg.source_system,
                                                    source_component=cfg.source_component, autoreconnect=False)
        except Exception as e:  # socket.error, serial.SerialException, ValueError for a bad address
            raise DriverError(f"mavlink driver {self.robot_id}: cannot open {cfg.connection}: {e}") from e
        self._datagrams = isinstance(self._conn, mavutil.mavudp)
        self._enc = mav.MAVLink(self._conn, srcSystem=cfg.source_system, srcComponent=cfg.source_component)

    def _handshake(self) -> None:
        """GUIDED accepted: see it in the heartbeat, ask for telemetry, arm and see it armed."""
        cfg = self.config
        self._wait_state(lambda: self._custom_mode == MODE_GUIDED, cfg.mode_timeout,
                         lambda: f"mode GUIDED not confirmed: the vehicle's heartbeat still shows "
                                 f"{self.vehicle_mode} {cfg.mode_timeout:g} s after MAV_RESULT_ACCEPTED")
        if cfg.set_ekf_origin:
            self._set_origin()
        streams = [("LOCAL_POSITION_NED", cfg.position_rate), ("ATTITUDE", cfg.attitude_rate)]
        if cfg.datum is not None:
            streams.append(("GLOBAL_POSITION_INT", cfg.position_rate))
        for name, rate in streams:
            self._command(f"message interval for {name}", mav.MAV_CMD_SET_MESSAGE_INTERVAL, TELEMETRY[name], 1e6 / rate)
        self._command("arming", mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        self._wait_state(self._is_armed, cfg.arm_timeout,
                         lambda: f"arming not confirmed: the vehicle's heartbeat shows it disarmed "
                                 f"{cfg.arm_timeout:g} s after MAV_RESULT_ACCEPTED")
        self._alive("heartbeat")  # the heartbeat timeout counts from here

    def _set_origin(self) -> None:
        """SET_GPS_GLOBAL_ORIGIN at the datum (a message: no ACK), resent until the vehicle's GPS_GLOBAL_ORIGIN says
        so; a vehicle that keeps its own origin is a warning (the fixes come from GLOBAL_POSITION_INT anyway)."""
        cfg = self.config
        want = origin_e7(cfg.datum)
        for _ in range(1 + cfg.command_retries):
            self._tx(self._encoder().set_gps_global_origin_encode(cfg.target_system, *want,
                                                                  max(0, int(self._stamp() * 1e6))))
            with self._state:
                if self._state.wait_for(lambda: self._origin is not None and origin_e7(self._origin) == want,
                                        cfg.ack_timeout):
                    self.count("origin_set")
                    return
        self.count("origin_refused")
        log.warning("mavlink driver %s: the vehicle kept its EKF origin %s (asked for the datum %s): LOCAL_POSITION_NED "
                    "stays relative to it; position fixes are GLOBAL_POSITION_INT around the datum", self.robot_id,
                    self.ekf_origin or "(not reported)", cfg.datum)

    def _wait_heartbeat(self) -> None:
        cfg = self.config
        with self._state:
            if not self._state.wait_for(lambda: self._hb_count > 0, cfg.connect_timeout):
                raise DriverError(f"mavlink driver {self.robot_id}: no HEARTBEAT from system {cfg.target_system} "
                                  f"component {cfg.target_component} on {cfg.connection} within "
                                  f"{cfg.connect_timeout:g} s")
            if self._vehicle_type != mav.MAV_TYPE_GROUND_ROVER:
                raise DriverError(f"mavlink driver {self.robot_id}: system {cfg.target_system} is "
                                  f"{enum_name('MAV_TYPE', self._vehicle_type)}, not MAV_TYPE_GROUND_ROVER")

    def _wait_state(self, pred: Callable[[], bool], timeout: float, why: Callable[[], str]) -> None:
        with self._state:
            if not self._state.wait_for(pred, timeout):
                raise DriverError(f"mavlink driver {self.robot_id}: {why()}")

    def _close(self) -> None:
        age = self.age("heartbeat")
        if self._taken_over:
            log.warning("mavlink driver %s: the vehicle left our control (%s): its mode and arming stay as they are",
                        self.robot_id, self.fault)
        else:
            self._release(wait=age is not None and age <= self.config.heartbeat_timeout)
        self._teardown()

    def _release(self, wait: bool) -> None:
        """Zero target, HOLD, disarm: waiting for each ACK when the vehicle is there to answer."""
        steps = (("HOLD on close", mav.MAV_CMD_DO_SET_MODE, (mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MODE_HOLD)),
                 ("disarming on close", mav.MAV_CMD_COMPONENT_ARM_DISARM, (0,)))
        try:
            with self._lock:
                self._send(0.0, 0.0)
            for what, command, params in steps:
                if wait:
                    try:
                        self._command(what, command, *params)
                    except DriverError as e:
                        self.count("close_refused")
                        log.warning("%s", e)
                else:
                    self._tx_command(command, 0, *params)
        except (OSError, DriverError) as e:  # the link itself is gone: closing must still finish
            log.warning("mavlink driver %s: release on close failed: %s", self.robot_id, e)

    def _teardown(self) -> None:
        self._stop_supervisor()
        with self._tx_lock:
            if self._conn is not None:
                try:
                    self._conn.close()
                except OSError as e:
                    log.warning("mavlink driver %s: close of %s failed: %s", self.robot_id, self.config.connection, e)
                self._conn = None

    # --- commands ---------------------------------------------------------------------
    def _send(self, v: float, w: float) -> None:
        cfg = self.config
        try:
            self._tx(self._encoder().set_position_target_local_ned_encode(
                self._boot_ms(), cfg.target_system, cfg.target_component, mav.MAV_FRAME_BODY_NED,
                TYPE_MASK_VEL_YAW_RATE, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, yaw_rate_ned(w)))
        except OSError as e:
            raise DriverError(f"mavlink driver {self.robot_id}: send failed on {cfg.connection}: {e}") from e

    def _set_mode(self, mode: int, name: str) -> None:
        self._command(f"mode {name}", mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)

    def _command(self, what: str, command: int, *params: float) -> None:
        """COMMAND_LONG until its COMMAND_ACK (resent on silence); anything but ACCEPTED raises DriverError."""
        cfg = self.config
        ack = None
        for attempt in range(1 + cfg.command_retries):
            with self._state:
                self._acks.pop(command, None)
            self._tx_command(command, attempt, *params)
            ack = self._await_ack(command)
            if ack is not None:
                break
            self.count("ack_timeout")
        if ack is None:
            raise DriverError(f"mavlink driver {self.robot_id}: {what}: no COMMAND_ACK for "
                              f"{enum_name('MAV_CMD', command)} within {cfg.ack_timeout:g} s "
                              f"({1 + cfg.command_retries} tries on {cfg.connection})")
        if ack.result != mav.MAV_RESULT_ACCEPTED:
            raise DriverError(f"mavlink driver {self.robot_id}: {what} refused: {result_name(ack.result)}")

    def _await_ack(self, command: int) -> Any:
        """The final COMMAND_ACK of ``command`` within ``ack_timeout`` (an IN_PROGRESS one extends it), or None."""
        timeout = self.config.ack_timeout
        deadline = time.monotonic() + timeout
        with self._state:
            while True:
                ack = self._acks.get(command)
                if ack is not None and ack.result != mav.MAV_RESULT_IN_PROGRESS:
                    return ack
                if ack is not None:  # IN_PROGRESS: the final ACK follows; do not resend
                    deadline = max(deadline, time.monotonic() + timeout)
                    self._acks.pop(command, None)
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._state.wait(left)

    def _tx_command(self, command: int, confirmation: int, *params: float) -> None:
        p = (list(params) + [0.0] * 7)[:7]
        self._tx(self._encoder().command_long_encode(self.config.target_system, self.config.target_component,
                                                     command, confirmation, *p))

    def _send_heartbeat(self) -> None:
        self._tx(self._encoder().heartbeat_encode(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0,
                                                  mav.MAV_STATE_ACTIVE))

    def _tx(self, msg: Any) -> None:
        with self._tx_lock:
            if self._conn is None or self._enc is None:
                raise OSError("link is closed")
            self._enc.send(msg)  # packs with our ids and sequence, then the link's write()
        self.count("tx")

    def _encoder(self) -> mav.MAVLink:
        if self._enc is None:
            raise OSError("link is closed")
        return self._enc

    def _boot_ms(self) -> int:
        return int((time.monotonic() - self._boot) * 1000) & 0xFFFFFFFF

    # --- receiving (the supervise thread's _poll) ----------------------------------------
    @staticmethod
    def _new_parser() -> mav.MAVLink:
        p = mav.MAVLink(None)
        p.robust_parsing = True  # bad bytes come back as BAD_DATA messages, never as exceptions
        return p

    def _poll(self, timeout: float) -> None:
        """Receive for up to ``timeout`` s: one datagram (or serial chunk), parsed and handled."""
        conn = self._conn
        if conn is None:
            self._halt.wait(timeout)
            return
        try:
            if not conn.select(timeout):
                return
            data = conn.recv(self._parser.bytes_needed())
        except (OSError, ValueError) as e:  # a closed socket, an unplugged serial adapter
            if not self._halt.is_set():
                self.count("rx_error")
                log.warning("mavlink driver %s: receive failed on %s: %s", self.robot_id, self.config.connection, e)
                self._halt.wait(0.1)
            return
        if data:
            self._parse(data)

    def _parse(self, data: bytes) -> None:
        msgs = self._parser.parse_buffer(data) or []
        if self._datagrams and self._parser.buf_len() > 0:  # a packet cut short: it never spans datagrams
            self._parser = self._new_parser()
            self.count("truncated", malformed=True)
        for m in msgs:
            try:
                self._on_message(m)
            except Exception:  # a handler bug must not kill the link
                self.count("handler_error")
                log.exception("mavlink driver %s: handling %s failed", self.robot_id, m.get_type())

    def _on_message(self, m: Any) -> None:
        kind = m.get_type()
        if kind == "BAD_DATA":
            return self.count("bad_crc" if "CRC" in str(m.reason) else "bad_data", malformed=True)
        if kind.startswith("UNKNOWN_"):
            return self.count("unknown_msg", malformed=True)
        cfg = self.config
        if m.get_srcSystem() != cfg.target_system:
            return self.count("other_system", malformed=True)
        if m.get_srcComponent() != cfg.target_component:
            return self.count("other_component")  # a camera, a gimbal: not ours to follow
        handler = {"HEARTBEAT": self._on_heartbeat, "COMMAND_ACK": self._on_ack,
                   "LOCAL_POSITION_NED": self._on_position, "ATTITUDE": self._on_attitude,
                   "GLOBAL_POSITION_INT": self._on_global, "GPS_GLOBAL_ORIGIN": self._on_origin}.get(kind)
        if handler is None:
            return self.count("ignored")
        handler(m)

    def _on_heartbeat(self, m: Any) -> None:
        armed = bool(m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
        custom = m.custom_mode if m.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED else None
        with self._state:
            self._hb_count += 1
            self._alive("heartbeat")
            self._vehicle_type, self._custom_mode, self._base_mode = m.type, custom, m.base_mode
            self.count("heartbeat")
            self._state.notify_all()
        if not self._supervising:
            return
        why = []
        if custom != MODE_GUIDED:
            why.append(f"vehicle left GUIDED, now in {mode_name(custom) if custom is not None else 'no custom mode'}")
        if not armed:
            why.append("vehicle disarmed")
        if why:
            with self._lock:  # the vehicle is someone else's only if this is the fault that trips
                self._taken_over = self._taken_over or (self.fault is None and self._supervising)
                self._trip(" and ".join(why))

    def _is_armed(self) -> bool:
        return bool(self._base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)

    def _on_ack(self, m: Any) -> None:
        if m.target_system not in (0, self.config.source_system):
            return self.count("ack_not_ours")
        with self._state:
            self._acks[m.command] = m
            self.count("ack")
            self._state.notify_all()

    def _on_position(self, m: Any) -> None:
        if not all(math.isfinite(x) for x in (m.x, m.y, m.vx, m.vy)):
            return self.count("bad_value", malformed=True)
        with self._state:
            self._pos, self._pos_fresh = m, True
        self._alive("local_position")
        self.count("local_position")
        self._odometry()

    def _on_global(self, m: Any) -> None:
        """GLOBAL_POSITION_INT (with a datum): the site-frame position fix, on the datum's tangent plane."""
        datum = self.config.datum
        if datum is None:
            return self.count("ignored")
        lat, lon, alt = m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            return self.count("bad_value", malformed=True)
        if m.lat == 0 and m.lon == 0:  # ArduPilot's "no position estimate yet"
            return self.count("no_global_fix")
        x, y = geodetic_to_site(datum, lat, lon, alt)
        with self._state:
            self._fix = (x, y, self.config.position_std, self._stamp())
        self._alive("global_position")
        self.count("global_position")

    def _on_origin(self, m: Any) -> None:
        """GPS_GLOBAL_ORIGIN: where the vehicle's LOCAL_POSITION_NED is from."""
        with self._state:
            self._origin = (m.latitude * 1e-7, m.longitude * 1e-7, m.altitude * 1e-3)
            self._state.notify_all()
        self.count("gps_global_origin")

    def _on_attitude(self, m: Any) -> None:
        if not all(math.isfinite(x) for x in (m.yaw, m.yawspeed)):
            return self.count("bad_value", malformed=True)
        with self._state:
            self._att, self._att_fresh = m, True
        self._alive("attitude")
        self.count("attitude")
        self._odometry()

    def _odometry(self) -> None:
        """A fresh position + attitude pair -> one odometry sample and one position fix."""
        with self._state:
            if not (self._pos_fresh and self._att_fresh):
                return
            self._pos_fresh = self._att_fresh = False
            p, a = self._pos, self._att
            stamp = self._stamp()
            pose = ned_to_world(p.x, p.y, a.yaw)
            odo = self._latest = Odometry(v=forward_speed(p.vx, p.vy, a.yaw), w=yaw_rate_ned(a.yawspeed), stamp=stamp,
                                          pose=pose)
            if self.config.datum is None:  # with one, fixes are GLOBAL_POSITION_INT's (_on_global)
                self._fix = (pose[0], pose[1], self.config.position_std, stamp)
        self._alive("odom")
        if self._on_odom is not None:
            self._on_odom(odo)

    def _read(self) -> Odometry | None:
        with self._state:
            return self._latest

    def position_fix(self) -> tuple[float, float, float, float] | None:
        """The vehicle's newest own position estimate (x, y, position_std, stamp), or None before one: with a
        datum its GLOBAL_POSITION_INT in the site frame; without, its LOCAL_POSITION_NED (from its EKF origin)."""
        with self._state:
            return self._fix

    @property
    def ekf_origin(self) -> Datum | None:
        """(lat, lon, alt) of the vehicle's EKF origin from its newest GPS_GLOBAL_ORIGIN; None before one."""
        with self._state:
            return self._origin

    @property
    def vehicle_mode(self) -> str | None:
        """The mode in the vehicle's newest heartbeat (``GUIDED``), None before one."""
        with self._state:
            return None if self._custom_mode is None else mode_name(self._custom_mode)

    @property
    def vehicle_armed(self) -> bool:
        with self._state:
            return self._is_armed()

    # --- supervision hooks (the base's supervisor calls them) --------------------------
    @property
    def supervise_period(self) -> float:
        """A fifth of the heartbeat_timeout (and 20 ms at most) between supervision rounds."""
        return min(0.02, self.config.heartbeat_timeout / 5)

    def _keepalives(self) -> list[Keepalive]:
        """Our GCS heartbeat (always: the FS_GCS failsafe listens for it through the handshake) and the
        last target (while armed and not faulted)."""
        cfg = self.config
        return [Keepalive("gcs_heartbeat", cfg.heartbeat_period, self._send_heartbeat, faulted=True, always=True),
                Keepalive("command", cfg.keepalive_period)]

    def _health(self, now: float) -> str | None:
        """The vehicle's HEARTBEAT older than ``heartbeat_timeout`` on the driver's clock is a fault."""
        age = self.age("heartbeat", now)
        if age is not None and age > self.config.heartbeat_timeout:
            return f"no HEARTBEAT from system {self.config.target_system} for {age:.1f} s"
        return None

    def _keepalive_failed(self, keepalive: Keepalive, error: Exception) -> str | None:
        return f"send failed on {self.config.connection}: {error.__cause__ or error}"


__all__ = ["MODE_GUIDED", "MODE_HOLD", "ROVER_MODES", "TYPE_MASK_VEL_YAW_RATE", "MavlinkConfig", "MavlinkDriver",
           "forward_speed", "mode_name", "mode_number", "ned_to_world", "ned_velocity", "origin_e7", "result_name",
           "world_to_ned", "wrap_angle", "yaw_rate_ned"]
