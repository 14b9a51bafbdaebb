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
velocity targets only in body frames (8, 9), other target kinds are ignored and counted.
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

from ..drivers.mavlink import (MODE_GUIDED, MODE_HOLD, POSITION_IGNORE, ROVER_MODES, VX_IGNORE, YAW_RATE_IGNORE,
                               mode_name, mode_number, ned_velocity, world_to_ned, wrap_angle, yaw_rate_ned)

STREAMS = {mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "LOCAL_POSITION_NED", mav.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
           mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "GLOBAL_POSITION_INT"}
"""Message ids the rover streams when asked (MAV_CMD_SET_MESSAGE_INTERVAL)."""

_EARTH_RADIUS = 6_378_137.0  # [m] WGS-84, for the flat-earth GLOBAL_POSITION_INT


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
    ``home``: (lat, lon) [deg] of the local origin, for GLOBAL_POSITION_INT.
    ``integrate_pose``: the rover moves its own pose with its body velocity (standalone, tests);
    False when the world owns the pose and calls ``set_pose`` every step.
    """

    def __init__(self, bind: tuple[str, int] = ("127.0.0.1", 0), peer: tuple[str, int] | None = None, *,
                 system: int = 1, component: int = 1, gcs_system: int = 255, mode: str = "HOLD",
                 heartbeat_period: float = 1.0, target_timeout: float = 3.0, fs_gcs_timeout: float = 5.0,
                 accel_max: float = 1.0, yaw_accel_max: float = 3.0, speed_max: float = 2.0, turn_rate_max: float = 4.0,
                 default_rates: dict[int, float] | None = None, pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 home: tuple[float, float] = (-35.363261, 149.165230), integrate_pose: bool = True,
                 clock: Callable[[], float] = time.monotonic, log_size: int = 10_000):
        self.system, self.component, self.gcs_system = system, component, gcs_system
        self.heartbeat_period = heartbeat_period
        self.target_timeout = target_timeout
        self.fs_gcs_timeout = fs_gcs_timeout
        self.accel_max, self.yaw_accel_max = accel_max, yaw_accel_max
        self.speed_max, self.turn_rate_max = speed_max, turn_rate_max
        self.home = home
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
            return
        if kind == "SET_MODE":
            if m.target_system != self.system:
                return _count(self.counters, "not_for_us")
            ok = bool(m.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) and self._set_mode(m.custom_mode)
            result = mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_FAILED
            self._enc.send(self._enc.command_ack_encode(mav.MAVLINK_MSG_ID_SET_MODE, result, 0, 0, m.get_srcSystem(),
                                                        m.get_srcComponent()))
            return
        if kind == "SET_POSITION_TARGET_LOCAL_NED":
            if m.target_system != self.system:
                return _count(self.counters, "not_for_us")
            return self._on_target(m, t)
        _count(self.counters, "ignored")

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
            self.target, self.target_time = (0.0, 0.0), None  # a new mode starts without a GUIDED target
        return True

    def _on_target(self, m: Any, t: float) -> None:
        if not (self.armed and self.mode == MODE_GUIDED):
            return _count(self.counters, "target_refused")
        if m.coordinate_frame not in (mav.MAV_FRAME_BODY_NED, mav.MAV_FRAME_BODY_OFFSET_NED) \
                or m.type_mask & POSITION_IGNORE != POSITION_IGNORE or m.type_mask & VX_IGNORE:
            return _count(self.counters, "target_unsupported")
        yaw_rate = 0.0 if m.type_mask & YAW_RATE_IGNORE else m.yaw_rate
        if not (math.isfinite(m.vx) and math.isfinite(yaw_rate)):
            return _count(self.counters, "bad_value")
        v = max(-self.speed_max, min(self.speed_max, m.vx))
        w = max(-self.turn_rate_max, min(self.turn_rate_max, yaw_rate_ned(yaw_rate)))
        self.target, self.target_time = (v, w), t
        _count(self.counters, "target")

    def _advance(self, t: float) -> None:
        if self._t is None:
            self._t = self._t0 = self._next_hb = t
            for msg_id in self.intervals:
                self._next_stream[msg_id] = t
        if self.target_time is not None and t - self.target_time > self.target_timeout:
            self.target, self.target_time = (0.0, 0.0), None
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
        v_goal, w_goal = self.target if (self.armed and self.mode == MODE_GUIDED) else (0.0, 0.0)
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
        if t >= self._next_hb:
            if not self.heartbeats_stopped:
                self._send_heartbeat()
            self._next_hb = _next_due(self._next_hb, self.heartbeat_period, t)
        for msg_id, period in self.intervals.items():
            if period > 0 and t >= self._next_stream.get(msg_id, t):
                self._send_stream(msg_id, t)
                self._next_stream[msg_id] = _next_due(self._next_stream.get(msg_id, t), period, t)

    # --- messages out -------------------------------------------------------------------
    def _send_heartbeat(self) -> None:
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        status = mav.MAV_STATE_ACTIVE if self.armed else mav.MAV_STATE_STANDBY
        self._enc.send(self._enc.heartbeat_encode(mav.MAV_TYPE_GROUND_ROVER, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base,
                                                  self.mode, status))
        _count(self.counters, "heartbeat")

    def _send_stream(self, msg_id: int, t: float) -> None:
        north, east, yaw_ned = world_to_ned(self._x, self._y, self._yaw)
        v, w = self._measured or (self._v, self._w)
        vn, ve = ned_velocity(v, yaw_ned)
        ms = int((t - self._t0) * 1000) & 0xFFFFFFFF
        if msg_id == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            msg = self._enc.local_position_ned_encode(ms, north, east, 0.0, vn, ve, 0.0)
        elif msg_id == mav.MAVLINK_MSG_ID_ATTITUDE:
            msg = self._enc.attitude_encode(ms, 0.0, 0.0, yaw_ned, 0.0, 0.0, yaw_rate_ned(w))
        else:
            lat = self.home[0] + math.degrees(north / _EARTH_RADIUS)
            lon = self.home[1] + math.degrees(east / (_EARTH_RADIUS * math.cos(math.radians(self.home[0]))))
            msg = self._enc.global_position_int_encode(ms, int(lat * 1e7), int(lon * 1e7), 0, 0, int(vn * 100),
                                                       int(ve * 100), 0, int(math.degrees(yaw_ned) % 360 * 100))
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
            self.target, self.target_time = (0.0, 0.0), None


def _next_due(due: float, period: float, t: float) -> float:
    due += period
    return due if due > t else t + period


__all__ = ["STREAMS", "SimRover"]
