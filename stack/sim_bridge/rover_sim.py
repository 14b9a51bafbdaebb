"""A simulated ArduPilot Rover autopilot speaking MAVLink 2 (ardupilotmega) over UDP.

``SimRover`` keeps what the MAVLink driver sees of a rover: HEARTBEAT at 1 Hz
(``MAV_TYPE_GROUND_ROVER``, ``MAV_AUTOPILOT_ARDUPILOTMEGA``, custom_mode = the mode,
base_mode with ``CUSTOM_MODE_ENABLED`` and ``SAFETY_ARMED`` when armed); modes set by
``COMMAND_LONG`` ``MAV_CMD_DO_SET_MODE`` and by the ``SET_MODE`` message; arming
(``MAV_CMD_COMPONENT_ARM_DISARM``, refused with ``MAV_RESULT_DENIED`` while
``arming_check_failed``); a ``COMMAND_ACK`` for every ``COMMAND_LONG`` (``UNSUPPORTED`` for
commands it lacks); GUIDED body-frame velocity + yaw-rate targets
(``SET_POSITION_TARGET_LOCAL_NED``), ignored and counted unless armed and in GUIDED; the
3 s target timeout (stops); the FS_GCS failsafe (no heartbeat from the GCS system id for
``fs_gcs_timeout`` while armed -> HOLD); ``LOCAL_POSITION_NED``, ``ATTITUDE`` and
``GLOBAL_POSITION_INT`` at the rates asked for by ``MAV_CMD_SET_MESSAGE_INTERVAL`` (off
until asked, as ``default_rates`` says).

Ground-station traffic, as ArduPilot answers it (``GCS_MAVLINK`` / ``Rover/GCS_MAVLink_Rover.cpp``):
telemetry only when asked, by ``REQUEST_DATA_STREAM`` (the stream groups POSITION,
EXTRA1, EXTENDED_STATUS and ALL; no ACK, as it is a message), ``MAV_CMD_SET_MESSAGE_INTERVAL``,
``MAV_CMD_GET_MESSAGE_INTERVAL`` and ``MAV_CMD_REQUEST_MESSAGE`` (each ACKed; FAILED for a
message it does not have), ``AUTOPILOT_VERSION`` on request (how a ground station identifies
it); HEARTBEAT base_mode with ``GUIDED_ENABLED`` in the autopilot modes (GUIDED, AUTO, RTL,
SMART_RTL, LOITER), ``MANUAL_INPUT_ENABLED`` in MANUAL, ACRO and STEERING, ``SAFETY_ARMED``
when armed; system status CRITICAL in a failsafe, STANDBY in HOLD, ACTIVE otherwise
(``vehicle_system_status``). ``SET_POSITION_TARGET_LOCAL_NED`` is read as
``handle_set_position_target_local_ned`` does, with Rover's ``defines.h`` masks (any bit of
a group set ignores the group: position x|y, velocity vx|vy, acceleration ax|ay, yaw, yaw
rate): frames LOCAL_NED (from the EKF origin), LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED;
acceleration not ignored -> rejected with a STATUSTEXT; a position -> drive there (stop
within ``wp_radius``); velocity (+ turn rate, or + heading, or alone: heading from its
direction) -> speed |(vx, vy)|, backwards when vx < 0 and a yaw or yaw rate is given; a
turn rate or a heading alone -> turn on the spot. Velocity and heading targets time out after
3 s; a position target does not.

Frames and the globe: the world's (site) frame has its origin at ``datum`` (lat, lon, alt)
and maps to the globe through the datum's WGS 84 local tangent plane (north = y, east = x;
``stack.models.geodesy``, the conversion the MAVLink driver reads GLOBAL_POSITION_INT with).
``LOCAL_POSITION_NED`` is relative to the EKF origin: the datum by default, where the
rover booted with ``origin_at_boot`` (ArduPilot sets it at its first fix), or what
``SET_GPS_GLOBAL_ORIGIN`` says (answered with ``GPS_GLOBAL_ORIGIN``). ``GLOBAL_POSITION_INT``: lat/lon degE7 and alt mm from the datum,
relative_alt 0 (flat ground, home at boot), vx/vy/vz cm/s NED, hdg cdeg.

It is driven by its caller's time, like ``odrive_sim.ODrivePair``: ``step(t_now)`` handles
the datagrams that came in, advances a unicycle body (speed and turn rate ramp to the
target under acceleration limits) to ``t_now`` and sends the messages due by then, so the
pybullet world can run it in lock-step sim time; ``run_realtime()`` steps it from a thread
on wall time. The world owns the pose: it reads ``body_velocity()`` (what the rover's
controllers drive the wheels with) and writes back the pose it simulated with
``set_pose(x, y, yaw[, v, w])`` in our world frame; telemetry is sent in NED.

Wire: a UDP socket bound to ``bind`` (loopback, any free port by default: ``port``). It
sends to ``peer`` when given (as ArduPilot SITL sends to a GCS on 14550: the driver listens
with ``udpin:``), else to every address that has sent to it (the driver connects with
``udpout:``).

Not vendor behaviour: arming in any mode and without checks but ``arming_check_failed``;
``MAV_RESULT_DENIED`` for a failed arming check (ArduPilot says FAILED and a STATUSTEXT);
heading and position targets are steered by a proportional heading controller (``HEADING_P``)
at up to ``speed_max``, not by Rover's navigation controllers (L1 / S-curves, WP_SPEED).
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time
from collections import deque
from typing import Any, Callable

from pymavlink.dialects.v20 import ardupilotmega as mav

from ..drivers.mavlink import (MODE_GUIDED, MODE_HOLD, ROVER_MODES, mode_name, mode_number, ned_velocity,
                               ned_to_world, origin_e7, world_to_ned, wrap_angle, yaw_rate_ned)
from ..models.geodesy import geodetic_to_ne, geodetic_to_site, ne_to_geodetic, site_to_geodetic

STREAMS = {mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "LOCAL_POSITION_NED", mav.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
           mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "GLOBAL_POSITION_INT", mav.MAVLINK_MSG_ID_SYS_STATUS: "SYS_STATUS"}
"""Message ids the rover streams when asked (MAV_CMD_SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM)."""
ONCE = {**STREAMS, mav.MAVLINK_MSG_ID_HEARTBEAT: "HEARTBEAT", mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: "GPS_GLOBAL_ORIGIN",
        mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: "AUTOPILOT_VERSION"}
"""Message ids it sends once on MAV_CMD_REQUEST_MESSAGE."""
DATA_STREAMS = {mav.MAV_DATA_STREAM_EXTENDED_STATUS: (mav.MAVLINK_MSG_ID_SYS_STATUS,),
                mav.MAV_DATA_STREAM_POSITION: (mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                                               mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
                mav.MAV_DATA_STREAM_EXTRA1: (mav.MAVLINK_MSG_ID_ATTITUDE,)}
"""REQUEST_DATA_STREAM groups (ArduPilot's stream contents, restricted to the messages it has)."""
FIRMWARE = (4, 5, 7)
"""Rover firmware (major, minor, patch) in AUTOPILOT_VERSION (an official release: type 255)."""
CAPABILITIES = (mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT)
"""AUTOPILOT_VERSION capabilities: the subset of ArduPilot's ``GCS_MAVLINK::capabilities()`` this rover has."""
TIME_EPS = 1e-9  # [s] times this close are the same tick (n periods and a caller's n steps agree to rounding)
MAX_STREAM_HZ = 50.0  # ArduPilot caps a stream at its main loop rate; Rover runs at 50 Hz

AUTOPILOT_MODES = {ROVER_MODES[m] for m in ("GUIDED", "AUTO", "RTL", "SMART_RTL", "LOITER", "FOLLOW", "DOCK")
                   if m in ROVER_MODES}
"""Modes whose ``is_autopilot_mode()`` is true: HEARTBEAT base_mode has MAV_MODE_FLAG_GUIDED_ENABLED."""
MANUAL_MODES = {ROVER_MODES[m] for m in ("MANUAL", "ACRO", "STEERING")}
"""Modes whose ``has_manual_input()`` is true: MAV_MODE_FLAG_MANUAL_INPUT_ENABLED."""

# Rover/defines.h: SET_POSITION_TARGET type_mask groups (any bit set ignores the group)
MASK_POS_IGNORE = (1 << 0) | (1 << 1)
MASK_VEL_IGNORE = (1 << 3) | (1 << 4)
MASK_ACC_IGNORE = (1 << 6) | (1 << 7)
MASK_YAW_IGNORE = 1 << 10
MASK_YAW_RATE_IGNORE = 1 << 11
TARGET_FRAMES = (mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_LOCAL_OFFSET_NED, mav.MAV_FRAME_BODY_NED,
                 mav.MAV_FRAME_BODY_OFFSET_NED)
BODY_FRAMES = (mav.MAV_FRAME_BODY_NED, mav.MAV_FRAME_BODY_OFFSET_NED)
HEADING_P = 2.0  # [1/s] turn rate per rad of heading error (ArduPilot's ATC_STR_ANG_P default)

DEFAULT_DATUM = (-35.363261, 149.165230, 584.0)
"""(lat, lon, alt) of a site without a datum: ArduPilot SITL's default location (CMAC)."""


def _count(counters: dict[str, int], key: str) -> None:
    counters[key] = counters.get(key, 0) + 1


def _ramp(value: float, target: float, rate: float, dt: float) -> float:
    step = rate * dt
    return target if abs(target - value) <= step else value + math.copysign(step, target - value)


class _Wire:
    """The encoder's file: each packed message becomes one datagram to every destination."""

    def __init__(self, rover: "SimRover"):
        self._rover = rover

    def write(self, buf: bytes) -> None:
        self._rover._sendto(buf)


class SimRover:
    """One simulated ArduPilot Rover on a UDP socket (system ``system``, autopilot component ``component``).

    ``mode``: the boot mode (``HOLD`` or ``MANUAL``). ``accel_max`` [m/s^2] and
    ``yaw_accel_max`` [rad/s^2] limit how fast the body follows its target, ``speed_max``
    [m/s] and ``turn_rate_max`` [rad/s] clamp the target. ``gcs_system``: the system id whose
    heartbeats feed the FS_GCS failsafe (ArduPilot's SYSID_MYGCS); the failsafe starts after
    the first one, as ArduPilot's does. ``pose``: the start pose in our world frame.
    ``datum``: (lat, lon[, alt]) [deg, m] of the site origin, for GLOBAL_POSITION_INT (``home`` is
its old name: (lat, lon)). ``origin_at_boot``: the EKF origin is where the rover starts
(``pose``), not the datum. ``wp_radius`` [m]: a position target is reached within it.
    ``integrate_pose``: the rover moves its own pose with its body velocity (standalone, tests);
    False when the world owns the pose and calls ``set_pose`` every step.
    """

    def __init__(self, bind: tuple[str, int] = ("127.0.0.1", 0), peer: tuple[str, int] | None = None, *,
                 system: int = 1, component: int = 1, gcs_system: int = 255, mode: str = "HOLD",
                 heartbeat_period: float = 1.0, target_timeout: float = 3.0, fs_gcs_timeout: float = 5.0,
                 accel_max: float = 1.0, yaw_accel_max: float = 3.0, speed_max: float = 2.0, turn_rate_max: float = 4.0,
                 default_rates: dict[int, float] | None = None, pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 home: tuple[float, float] | None = None, datum: tuple[float, ...] | None = None,
                 origin_at_boot: bool = False, wp_radius: float = 2.0, integrate_pose: bool = True,
                 clock: Callable[[], float] = time.monotonic, log_size: int = 10_000):
        self.system, self.component, self.gcs_system = system, component, gcs_system
        self.heartbeat_period = heartbeat_period
        self.target_timeout = target_timeout
        self.fs_gcs_timeout = fs_gcs_timeout
        self.accel_max, self.yaw_accel_max = accel_max, yaw_accel_max
        self.speed_max, self.turn_rate_max = speed_max, turn_rate_max
        lat0, lon0, *alt = datum if datum is not None else (home if home is not None else DEFAULT_DATUM)
        self.datum = (float(lat0), float(lon0), float(alt[0]) if alt else DEFAULT_DATUM[2])
        self.home = self.datum[:2]
        self.origin = site_to_geodetic(self.datum, pose[0], pose[1]) if origin_at_boot else self.datum
        """The EKF origin (lat, lon, alt): LOCAL_POSITION_NED is relative to it."""
        self.wp_radius = wp_radius
        self.guided: tuple[str, float, float] | None = None  # ("heading", v, yaw) or ("position", x, y): else rate
        self.integrate_pose = integrate_pose
        self.peer = peer
        self.mode = mode_number(mode)
        self.armed = False
        self.arming_check_failed = False  # test hook: arming is refused (MAV_RESULT_DENIED) while set
        self.heartbeats_stopped = False
        self.failsafe: str | None = None  # "GCS" while the GCS failsafe holds
        self.counters: dict[str, int] = {}
        self.rx_log: deque[tuple[float, Any]] = deque(maxlen=log_size)  # (t, decoded message) from others
        self.intervals: dict[int, float] = dict(default_rates or {})  # msg id -> period [s]; absent or 0: off
        self._default_rates = dict(self.intervals)
        self.target = (0.0, 0.0)  # (v, w) the GUIDED target in our convention (w counter-clockwise)
        self.target_time: float | None = None  # when the current target arrived
        self.gcs_time: float | None = None  # the GCS's newest heartbeat
        self._x, self._y, self._yaw = pose
        self._v = self._w = 0.0  # body velocity the rover drives (after the ramp)
        self._measured: tuple[float, float] | None = None  # body velocity the world measured, if it said
        self._clients: set[tuple[str, int]] = set()
        self._clock = clock
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._killed = False
        self._t: float | None = None
        self._t0: float | None = None
        self._next_hb = 0.0
        self._next_stream: dict[int, float] = {}
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(bind)
        self._sock.setblocking(False)
        self.address = self._sock.getsockname()
        self._enc = mav.MAVLink(_Wire(self), srcSystem=system, srcComponent=component)

    @property
    def port(self) -> int:
        return self.address[1]

    # --- lock-step ----------------------------------------------------------------------
    def step(self, t_now: float) -> None:
        """Handle every datagram received so far, advance the body to ``t_now``, send what is due.

        Messages received since the last step take effect at its start (a zero-order hold).
        """
        with self._lock:
            if self._killed:
                return
            self._receive(t_now)
            self._advance(t_now)
            self._emit(t_now)

    # the three parts of a step, for a world that moves the body between them
    def receive(self, t_now: float) -> None:
        """Handle every datagram received so far (targets act from ``t_now``)."""
        with self._lock:
            if not self._killed:
                self._receive(t_now)

    def advance(self, t_now: float) -> None:
        """Ramp the body velocity to ``t_now`` (timeouts, failsafe)."""
        with self._lock:
            if not self._killed:
                self._advance(t_now)

    def emit(self, t_now: float) -> None:
        """Send what is due by ``t_now`` (after ``set_pose``: telemetry of the body the world moved)."""
        with self._lock:
            if not self._killed:
                self._emit(t_now)

    def _receive(self, t: float) -> None:
        while True:
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP port unreachable from a peer that is gone
                _count(self.counters, "rx_error")
                continue
            if self.peer is None:
                self._clients.add(addr)
            parser = mav.MAVLink(None)  # one per datagram: a packet never spans two
            parser.robust_parsing = True
            for m in parser.parse_buffer(data) or []:
                self._handle(m, t)
            if parser.buf_len() > 0:
                _count(self.counters, "truncated")

    def _handle(self, m: Any, t: float) -> None:
        kind = m.get_type()
        if kind == "BAD_DATA":
            return _count(self.counters, "bad_data")
        if kind.startswith("UNKNOWN_"):
            return _count(self.counters, "unknown_msg")
        self.rx_log.append((t, m))
        _count(self.counters, "rx")
        if kind == "HEARTBEAT":
            if m.get_srcSystem() == self.gcs_system:
                self.gcs_time = t
                _count(self.counters, "gcs_heartbeat")
                if self.failsafe == "GCS":
                    self.failsafe = None  # the mode stays HOLD, as ArduPilot's does
            return
        if kind == "COMMAND_LONG":
            if m.target_system not in (0, self.system) or m.target_component not in (0, self.component):
                return _count(self.counters, "not_for_us")
            result = self._command(m, t)
            self._enc.send(self._enc.command_ack_encode(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()))
            if m.command == mav.MAV_CMD_REQUEST_MESSAGE and result == mav.MAV_RESULT_ACCEPTED:
                self._send_once(int(m.param1), t)  # after its ACK, as ArduPilot's deferred send
            return
        if kind == "SET_MODE":
            if m.target_system != self.system:
                return _count(self.counters, "not_for_us")
            ok = bool(m.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) and self._set_mode(m.custom_mode)
            result = mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_FAILED
            self._enc.send(self._enc.command_ack_encode(mav.MAVLINK_MSG_ID_SET_MODE, result, 0, 0, m.get_srcSystem(),
                                                        m.get_srcComponent()))
            return
        if kind in ("SET_POSITION_TARGET_LOCAL_NED", "REQUEST_DATA_STREAM", "SET_GPS_GLOBAL_ORIGIN"):
            if m.target_system != self.system:
                return _count(self.counters, "not_for_us")
            handler = {"SET_POSITION_TARGET_LOCAL_NED": self._on_target, "REQUEST_DATA_STREAM": self._on_data_stream,
                       "SET_GPS_GLOBAL_ORIGIN": self._on_origin}[kind]
            return handler(m, t)
        _count(self.counters, "ignored")

    def _on_data_stream(self, m: Any, t: float) -> None:
        """REQUEST_DATA_STREAM (no ACK: a message): start/stop a stream group at a rate [Hz]."""
        if m.start_stop == 0:
            rate = 0.0
        elif m.req_message_rate != 0:
            rate = min(float(m.req_message_rate), MAX_STREAM_HZ)
        else:
            return _count(self.counters, "ignored")
        groups = DATA_STREAMS.values() if m.req_stream_id == mav.MAV_DATA_STREAM_ALL else \
            [DATA_STREAMS.get(m.req_stream_id, ())]
        for msg_id in (i for group in groups for i in group):
            self.intervals[msg_id] = 1.0 / rate if rate > 0 else 0.0
            self._next_stream[msg_id] = t
        _count(self.counters, "data_stream")

    def _on_origin(self, m: Any, t: float) -> None:
        """SET_GPS_GLOBAL_ORIGIN: the EKF origin moves there (LOCAL_POSITION_NED follows); says GPS_GLOBAL_ORIGIN."""
        lat, lon = m.latitude * 1e-7, m.longitude * 1e-7
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            return _count(self.counters, "bad_value")
        self.origin = (lat, lon, m.altitude * 1e-3)
        _count(self.counters, "origin_set")
        self._send_once(mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, t)

    def _command(self, m: Any, t: float) -> int:
        c = m.command
        if c == mav.MAV_CMD_DO_SET_MODE:
            if not int(m.param1) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return mav.MAV_RESULT_DENIED
            return mav.MAV_RESULT_ACCEPTED if self._set_mode(int(m.param2)) else mav.MAV_RESULT_FAILED
        if c == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            if m.param1 == 1:
                if self.arming_check_failed:
                    _count(self.counters, "arming_refused")
                    return mav.MAV_RESULT_DENIED
                self.armed = True
                return mav.MAV_RESULT_ACCEPTED
            if m.param1 == 0:
                self.disarm()
                return mav.MAV_RESULT_ACCEPTED
            return mav.MAV_RESULT_DENIED
        if c == mav.MAV_CMD_REQUEST_MESSAGE:
            return mav.MAV_RESULT_ACCEPTED if int(m.param1) in ONCE else mav.MAV_RESULT_FAILED
        if c == mav.MAV_CMD_GET_MESSAGE_INTERVAL:
            msg_id = int(m.param1)
            if msg_id not in STREAMS:
                return mav.MAV_RESULT_FAILED
            period = self.intervals.get(msg_id, 0.0)
            self._enc.send(self._enc.message_interval_encode(msg_id, round(period * 1e6) if period > 0 else -1))
            return mav.MAV_RESULT_ACCEPTED
        if c == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval = int(m.param1), m.param2
            if msg_id not in STREAMS or not math.isfinite(interval):
                return mav.MAV_RESULT_FAILED
            if interval < 0:
                self.intervals[msg_id] = 0.0
            elif interval == 0:
                self.intervals[msg_id] = self._default_rates.get(msg_id, 0.0)
            else:
                self.intervals[msg_id] = interval * 1e-6
                self._next_stream[msg_id] = t
            return mav.MAV_RESULT_ACCEPTED
        _count(self.counters, "unsupported_command")
        return mav.MAV_RESULT_UNSUPPORTED

    def _set_mode(self, mode: int) -> bool:
        if mode not in ROVER_MODES.values() or mode == ROVER_MODES["INITIALIZING"]:
            return False
        if mode != self.mode:
            self.mode = mode
            self.target, self.target_time, self.guided = (0.0, 0.0), None, None  # a new mode: no GUIDED target
        return True

    def _on_target(self, m: Any, t: float) -> None:
        """SET_POSITION_TARGET_LOCAL_NED as ``handle_set_position_target_local_ned`` reads it (Rover's masks)."""
        if self.mode != MODE_GUIDED:
            return _count(self.counters, "target_refused")
        if m.coordinate_frame not in TARGET_FRAMES:
            return _count(self.counters, "target_unsupported")
        mask = m.type_mask
        pos, vel = not mask & MASK_POS_IGNORE, not mask & MASK_VEL_IGNORE
        yaw, rate = not mask & MASK_YAW_IGNORE, not mask & MASK_YAW_RATE_IGNORE
        used = (m.x, m.y) * pos + (m.vx, m.vy) * vel + (m.yaw,) * yaw + (m.yaw_rate,) * rate
        if not all(math.isfinite(f) for f in used):
            return _count(self.counters, "bad_value")
        if mask & MASK_ACC_IGNORE == 0:  # Rover ignores any target whose accelerations are not masked out
            self._statustext(mav.MAV_SEVERITY_INFO, "Ignoring SET_POSITION_TARGET_LOCAL_NED; set ACC_IGNORE in mask")
            return _count(self.counters, "target_accel_rejected")
        if pos:
            self.guided, self.target, self.target_time = ("position", *self._target_position(m)), (0.0, 0.0), None
            return _count(self.counters, "target")
        _, _, yaw_ned = world_to_ned(self._x, self._y, self._yaw)
        body = m.coordinate_frame in BODY_FRAMES
        speed = min(math.hypot(m.vx, m.vy), self.speed_max) if vel else 0.0
        heading = math.atan2(m.vy, m.vx) + (yaw_ned if body else 0.0) if vel else 0.0
        if yaw:
            heading = m.yaw + (yaw_ned if body else 0.0)
        if vel and (yaw or rate) and m.vx < 0:
            speed = -speed  # "by default the rover drives forward": vx < 0 reverses
        if vel and not rate or yaw and not vel and not rate:  # heading (and speed)
            self.guided = ("heading", speed, ned_to_world(0.0, 0.0, heading)[2])
            self.target = (speed, 0.0)
        elif rate and not yaw:  # turn rate (and speed)
            self.guided = None
            self.target = (speed, max(-self.turn_rate_max, min(self.turn_rate_max, yaw_rate_ned(m.yaw_rate))))
        else:  # yaw and yaw rate both, or nothing: Rover acts on neither
            return _count(self.counters, "target_unsupported")
        self.target_time = t
        _count(self.counters, "target")

    def _target_position(self, m: Any) -> tuple[float, float]:
        """The target's site position (x, y): LOCAL_NED from the EKF origin, the OFFSET/BODY frames from here."""
        if m.coordinate_frame == mav.MAV_FRAME_LOCAL_NED:
            lat, lon, _ = ne_to_geodetic(self.origin, m.x, m.y)
            return geodetic_to_site(self.datum, lat, lon)
        north, east = m.x, m.y
        if m.coordinate_frame in BODY_FRAMES:
            _, _, yaw_ned = world_to_ned(self._x, self._y, self._yaw)
            c, s = math.cos(yaw_ned), math.sin(yaw_ned)
            north, east = m.x * c - m.y * s, m.x * s + m.y * c
        return self._x + east, self._y + north

    def _goal_speeds(self) -> tuple[float, float]:
        """(v, w) the GUIDED controllers ask for now: the target's, or steering to a heading or a position."""
        if self.guided is None:
            return self.target
        kind, a, b = self.guided
        if kind == "heading":
            err = wrap_angle(b - self._yaw)
            return a, max(-self.turn_rate_max, min(self.turn_rate_max, HEADING_P * err))
        dx, dy = a - self._x, b - self._y
        dist = math.hypot(dx, dy)
        if dist <= self.wp_radius:
            return 0.0, 0.0
        err = wrap_angle(math.atan2(dy, dx) - self._yaw)
        v = min(self.speed_max, dist) * max(0.0, math.cos(err))
        return v, max(-self.turn_rate_max, min(self.turn_rate_max, HEADING_P * err))

    def _advance(self, t: float) -> None:
        if self._t is None:
            self._t = self._t0 = self._next_hb = t
            for msg_id in self.intervals:
                self._next_stream[msg_id] = t
        if self.target_time is not None and t - self.target_time > self.target_timeout:
            self.target, self.target_time, self.guided = (0.0, 0.0), None, None
            _count(self.counters, "target_timeout")
        if (self.armed and self.failsafe is None and self.gcs_time is not None
                and t - self.gcs_time > self.fs_gcs_timeout):
            self.failsafe = "GCS"
            _count(self.counters, "fs_gcs")
            self._set_mode(MODE_HOLD)
        dt = t - self._t
        if dt <= 0:
            return
        self._t = t
        v_goal, w_goal = self._goal_speeds() if (self.armed and self.mode == MODE_GUIDED) else (0.0, 0.0)
        v0, w0 = self._v, self._w
        self._v = _ramp(v0, v_goal, self.accel_max, dt)
        self._w = _ramp(w0, w_goal, self.yaw_accel_max, dt)
        if not self.integrate_pose:
            return
        v, w = 0.5 * (v0 + self._v), 0.5 * (w0 + self._w)
        yaw_mid = self._yaw + 0.5 * w * dt
        self._x += v * math.cos(yaw_mid) * dt
        self._y += v * math.sin(yaw_mid) * dt
        self._yaw = wrap_angle(self._yaw + w * dt)
        self._measured = None

    def _emit(self, t: float) -> None:
        if t + TIME_EPS >= self._next_hb:
            if not self.heartbeats_stopped:
                self._send_heartbeat()
            self._next_hb = _next_due(self._next_hb, self.heartbeat_period, t)
        for msg_id, period in self.intervals.items():
            if period > 0 and t + TIME_EPS >= self._next_stream.get(msg_id, t):
                self._send_stream(msg_id, t)
                self._next_stream[msg_id] = _next_due(self._next_stream.get(msg_id, t), period, t)

    # --- messages out -------------------------------------------------------------------
    def _send_heartbeat(self) -> None:
        base = (mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
                | (mav.MAV_MODE_FLAG_GUIDED_ENABLED if self.mode in AUTOPILOT_MODES else 0)
                | (mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED if self.mode in MANUAL_MODES else 0))
        self._enc.send(self._enc.heartbeat_encode(mav.MAV_TYPE_GROUND_ROVER, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base,
                                                  self.mode, self.system_status))
        _count(self.counters, "heartbeat")

    @property
    def system_status(self) -> int:
        """HEARTBEAT system_status as Rover's ``vehicle_system_status``."""
        if self.failsafe is not None:
            return mav.MAV_STATE_CRITICAL
        if self.mode == ROVER_MODES["INITIALIZING"]:
            return mav.MAV_STATE_CALIBRATING
        return mav.MAV_STATE_STANDBY if self.mode == MODE_HOLD else mav.MAV_STATE_ACTIVE

    def _statustext(self, severity: int, text: str) -> None:
        self._enc.send(self._enc.statustext_encode(severity, text.encode()[:50]))
        _count(self.counters, "statustext")

    def _send_autopilot_version(self) -> None:
        """AUTOPILOT_VERSION as ``GCS_MAVLINK::send_autopilot_version``: capabilities, firmware, a uid."""
        major, minor, patch = FIRMWARE
        uid = f"SIMROVER{self.system:03d}".encode()
        self._enc.send(self._enc.autopilot_version_encode(
            CAPABILITIES, major << 24 | minor << 16 | patch << 8 | 255, 0, 0, 0, bytes(8), bytes(8), bytes(8),
            0, 0, int.from_bytes(uid[:8], "little"), uid.ljust(18, b"\0")))
        _count(self.counters, "autopilot_version")

    def _send_once(self, msg_id: int, t: float) -> None:
        """One message on request (MAV_CMD_REQUEST_MESSAGE, a new origin)."""
        if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT:
            return self._send_heartbeat()
        if msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self._send_autopilot_version()
        if msg_id == mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            self._enc.send(self._enc.gps_global_origin_encode(*origin_e7(self.origin),
                                                              int(max(0.0, t - (self._t0 or 0.0)) * 1e6)))
            return _count(self.counters, "gps_global_origin")
        self._send_stream(msg_id, t)

    def _send_stream(self, msg_id: int, t: float) -> None:
        _, _, yaw_ned = world_to_ned(self._x, self._y, self._yaw)
        v, w = self._measured or (self._v, self._w)
        vn, ve = ned_velocity(v, yaw_ned)
        ms = int((t - (self._t0 if self._t0 is not None else t)) * 1000) & 0xFFFFFFFF
        lat, lon, alt = site_to_geodetic(self.datum, self._x, self._y)
        if msg_id == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            north, east = geodetic_to_ne(self.origin, lat, lon, alt)  # from the EKF origin
            msg = self._enc.local_position_ned_encode(ms, north, east, 0.0, vn, ve, 0.0)
        elif msg_id == mav.MAVLINK_MSG_ID_ATTITUDE:
            msg = self._enc.attitude_encode(ms, 0.0, 0.0, yaw_ned, 0.0, 0.0, yaw_rate_ned(w))
        elif msg_id == mav.MAVLINK_MSG_ID_SYS_STATUS:
            sensors = (mav.MAV_SYS_STATUS_SENSOR_3D_GYRO | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                       | mav.MAV_SYS_STATUS_SENSOR_3D_MAG | mav.MAV_SYS_STATUS_SENSOR_GPS)
            msg = self._enc.sys_status_encode(sensors, sensors, sensors, 100, 12_600, -1, -1, 0, 0, 0, 0, 0, 0)
        else:
            msg = self._enc.global_position_int_encode(ms, round(lat * 1e7), round(lon * 1e7), round(alt * 1e3), 0,
                                                       round(vn * 100), round(ve * 100), 0,
                                                       round(math.degrees(yaw_ned) % 360 * 100) % 36000)
        self._enc.send(msg)
        _count(self.counters, STREAMS[msg_id].lower())

    def _sendto(self, buf: bytes) -> None:
        for addr in ([self.peer] if self.peer is not None else list(self._clients)):
            try:
                self._sock.sendto(buf, addr)
                _count(self.counters, "tx")
            except OSError:  # nobody listening (ICMP unreachable), a full buffer: the radio drops it
                _count(self.counters, "tx_error")

    # --- wall time ----------------------------------------------------------------------
    def run_realtime(self, poll: float = 0.001) -> "SimRover":
        """Step on wall time from a thread; a datagram is handled as soon as it arrives."""
        if self._thread is None and not self._killed:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, args=(poll,), name="rover-sim", daemon=True)
            self._thread.start()
        return self

    def _run(self, poll: float) -> None:
        while not self._stop.is_set():
            try:
                select.select([self._sock], [], [], poll)
            except (OSError, ValueError):  # closed under us
                return
            self.step(self._clock())

    def stop(self) -> None:
        """Stop the realtime thread (the socket stays: ``step`` may go on in lock-step)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None

    def kill(self) -> None:
        """The autopilot is gone (power cut, cable out): nothing more on the wire, ever."""
        self.stop()
        with self._lock:
            self._killed = True
            self._sock.close()

    close = kill

    def __enter__(self) -> "SimRover":
        return self

    def __exit__(self, *exc) -> None:
        self.kill()

    # --- for the world ------------------------------------------------------------------
    def restart_timers(self, t: float) -> None:
        """The rover's clock is ``t`` from now on (its caller's clock changed hands: wall time to lock-step):
        the first heartbeat and stream messages are due a period after ``t``, the target timeout and the FS_GCS
        failsafe count from ``t`` (a target or GCS heartbeat it holds is as old as ``t``), and its uptime
        (``time_boot_ms``) is ``t`` (forward across the jump: the caller's clock is ahead of the wall phase)."""
        with self._lock:
            self._t, self._t0, self._next_hb = t, 0.0, t + self.heartbeat_period
            self._next_stream = {msg_id: t + period for msg_id, period in self.intervals.items()}
            self.target_time = t if self.target_time is not None else None
            self.gcs_time = t if self.gcs_time is not None else None

    def heartbeat(self) -> None:
        """One HEARTBEAT now, out of its schedule (a caller standing still); none while stopped or killed."""
        with self._lock:
            if not (self._killed or self.heartbeats_stopped):
                self._send_heartbeat()

    def body_velocity(self) -> tuple[float, float]:
        """(v [m/s], w [rad/s], counter-clockwise) the rover drives its body with now, in our convention."""
        with self._lock:
            return self._v, self._w

    def set_pose(self, x: float, y: float, yaw: float, v: float | None = None, w: float | None = None) -> None:
        """The pose the world simulated, in our world frame; ``v``, ``w``: the body velocity it measured
        (reported in telemetry until the rover next moves its own pose; without them it reports its own)."""
        with self._lock:
            self._x, self._y, self._yaw = x, y, wrap_angle(yaw)
            if v is not None and w is not None:
                self._measured = (v, w)

    @property
    def pose(self) -> tuple[float, float, float]:
        """(x, y, yaw) in our world frame."""
        with self._lock:
            return self._x, self._y, self._yaw

    @property
    def mode_name(self) -> str:
        return mode_name(self.mode)

    # --- test hooks ---------------------------------------------------------------------
    def force_mode(self, name: str) -> None:
        """The mode changes under the driver (an RC pilot's switch, a failsafe)."""
        with self._lock:
            if not self._set_mode(mode_number(name)):
                raise ValueError(f"rover sim: cannot switch to {name}")

    def stop_heartbeats(self, stopped: bool = True) -> None:
        """Heartbeats stop (telemetry goes on): a half-broken link, a hung autopilot task."""
        with self._lock:
            self.heartbeats_stopped = stopped

    def disarm(self) -> None:
        """Disarmed (a pilot's switch, the safety button): the motors stop driving."""
        with self._lock:
            self.armed = False
            self.target, self.target_time, self.guided = (0.0, 0.0), None, None


def _next_due(due: float, period: float, t: float) -> float:
    due += period
    return due if due > t + TIME_EPS else t + period


__all__ = ["DATA_STREAMS", "DEFAULT_DATUM", "ONCE", "STREAMS", "SimRover", "geodetic_to_ne", "geodetic_to_site",
           "ne_to_geodetic", "site_to_geodetic"]
