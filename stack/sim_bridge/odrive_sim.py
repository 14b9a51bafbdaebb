"""A simulated ODrive pair (CANSimple, firmware 0.6.x) and a simulated slcan USB-CAN adapter.

``SimAxis`` is one axis's state machine, without I/O: IDLE (1) -> CLOSED_LOOP_CONTROL (8) on
Set_Axis_State, a velocity ramp, heartbeats every 100 ms, encoder estimates every 10 ms and
on RTR, Estop, Clear_Errors, Set_Absolute_Position, the axis watchdog, and answers to every
"Get" request of the DBC (Get_Error, Get_Encoder_Estimates, Get_Bus_Voltage_Current, Get_Iq,
Get_Temperature, Get_Torques, Get_Powers, Get_Version). Its motor drives a load: torque =
inertia x angular acceleration + viscous friction x speed (the robot's mass at the wheel),
Iq = torque / torque constant, electrical power = mechanical + copper losses, the bus
current from that, temperatures ambient + losses x thermal resistance (steady state).

Encoders count from power-up: ``pos`` is the motor's turns since the axis powered up, from
``pos0`` (0 for an incremental encoder, the shaft angle for an absolute one), never the
robot's place in the world; Set_Absolute_Position sets it. ``all_samples``: every encoder
estimate due in a caller's step goes out, each at its own time (a real bus carries one
every 10 ms), instead of only the newest.

``ODrivePair`` puts two axes (any node ids) on any ``can.BusABC`` and is driven by its
caller's time: ``step(t_now)`` handles the frames that came in, advances the axes to
``t_now`` (sim time or wall time) and sends the frames due by then, so the pybullet world
can run it in lock-step sim time; ``run_realtime()`` steps it from a thread on wall time.
``vel(node)`` is the motor velocity [rev/s] as the ODrive counts it (``wheel_omega``
converts to wheel rad/s), for the world to turn the body's wheels.

``SlcanPtyBus`` is the adapter end of an slcan (Lawicel) USB-CAN adapter on a
pseudo-terminal, as a ``can.BusABC``: the host opens python-can's own ``slcan`` interface
on ``slave_path``; frames the host sends come out of ``recv()`` and frames given to
``send()`` reach the host. Two processes share a CAN bus this way with no kernel vcan::

    adapter = SlcanPtyBus()
    pair = ODrivePair(adapter, node_ids=(0, 1)).run_realtime()
    host = can.Bus(interface="slcan", channel=adapter.slave_path, bitrate=500000, sleep_after_open=0)

Vendor behaviour kept: every frame addressed to an axis feeds its watchdog (the vendor's
examples resend Set_Input_Vel within 0.5 s); errors stay until Clear_Errors and keep the
axis from closed loop. Not vendor behaviour: firmware 0.6 ignores a Set_Input_Vel in IDLE
silently; this axis sets ``INPUT_REJECTED_ERROR`` in its heartbeat, so a host that commands
before closed loop is seen (0.5 firmware flagged CONTROLLER_FAILED, which 0.6's DBC lacks).
"""

from __future__ import annotations

import errno
import math
import os
import select
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass
from typing import Callable

import can

from ..drivers import odrive
from ..drivers.odrive import AxisState, ControlMode, InputMode, ProcedureResult

TIME_EPS = 1e-9
"""[s] times this close are the same tick (a schedule of n periods and a caller's n steps agree to rounding)."""

INPUT_REJECTED_ERROR = "MISSING_INPUT"
"""Axis error (a DBC Axis_Error name) set by a Set_Input_Vel outside CLOSED_LOOP_CONTROL."""

FIRMWARE_VERSION = {"Protocol_Version": 2, "Hw_Version_Major": 4, "Hw_Version_Minor": 4, "Hw_Version_Variant": 58,
                    "Fw_Version_Major": 0, "Fw_Version_Minor": 6, "Fw_Version_Revision": 10, "Fw_Version_Unreleased": 0}
"""Get_Version of the simulated axis: an ODrive Pro (hw 4.4-58V) on firmware 0.6.10, the DBC's."""


@dataclass(frozen=True)
class MotorModel:
    """The motor and what it drives, for the torque, current, power and temperature replies."""

    torque_constant: float = 8.27 / 150.0
    """[Nm/A] 8.27 / KV (a 150 KV motor, the class of ODrive's D6374)."""
    inertia: float = 0.08
    """[kg m^2] at the motor: half a 17 kg robot at a 0.098 m wheel."""
    viscous: float = 0.02
    """[Nm per rev/s] rolling resistance and friction, proportional to speed."""
    phase_resistance: float = 0.04
    """[ohm] per phase (D6374: 0.039): copper losses 1.5 R Iq^2."""
    ambient: float = 25.0
    """[deg C] around the board."""
    fet_k_per_w: float = 0.1
    """[K/W] FET temperature rise per watt of losses (steady state)."""
    motor_k_per_w: float = 0.3
    """[K/W] motor temperature rise per watt of losses (steady state)."""

    def torque(self, vel: float, accel: float) -> float:
        """[Nm] to turn at ``vel`` [rev/s] while accelerating at ``accel`` [rev/s^2]."""
        return self.inertia * 2.0 * math.pi * accel + self.viscous * vel

    def copper_loss(self, iq: float) -> float:
        return 1.5 * self.phase_resistance * iq * iq


def _count(counters: dict[str, int], key: str) -> None:
    counters[key] = counters.get(key, 0) + 1


class SimAxis:
    """One ODrive axis in velocity control: state machine, ramp, watchdog, periodic frames.

    Time ``t`` [s] is whatever the caller steps with. The velocity tracks its setpoint
    exactly (an ideal controller); ``vel`` [rev/s] and ``pos`` [rev] are the motor's.
    Defaults are the vendor's: POSITION_CONTROL + PASSTHROUGH until Set_Controller_Mode.
    """

    def __init__(self, node_id: int, *, vel_ramp_rate: float = 10.0, watchdog_timeout: float = 0.5,
                 heartbeat_period: float = 0.1, encoder_period: float = 0.01, bus_voltage: float = 24.0,
                 pos0: float = 0.0, all_samples: bool = False, motor: "MotorModel | None" = None):
        self.node_id = node_id
        self.vel_ramp_rate = vel_ramp_rate  # [rev/s^2] the VEL_RAMP slope
        self.watchdog_timeout = watchdog_timeout  # [s] 0 disables the watchdog
        self.heartbeat_period = heartbeat_period
        self.encoder_period = encoder_period
        self.bus_voltage = bus_voltage
        self.state = AxisState.IDLE
        self.errors = 0  # active errors (Axis_Error of the heartbeat)
        self.conditions = 0  # error bits whose cause persists (see inject_error)
        self.disarm_reason = 0
        self.procedure_result = ProcedureResult.SUCCESS
        self.control_mode = ControlMode.POSITION_CONTROL
        self.input_mode = InputMode.PASSTHROUGH
        self.input_vel = 0.0  # [rev/s]
        self.vel = 0.0  # [rev/s]
        self.pos = float(pos0)  # [rev] since power-up (from the encoder's reading then)
        self.accel = 0.0  # [rev/s^2] over the newest integration step
        self.all_samples = all_samples
        self.motor = motor if motor is not None else MotorModel()
        self.heartbeats_muted = False
        self.counters: dict[str, int] = {}
        self._t: float | None = None
        self._fed = 0.0
        self._next_hb = 0.0
        self._next_enc = 0.0

    # --- frames in --------------------------------------------------------------------
    def handle(self, f: odrive.Frame, t: float) -> list[can.Message]:
        """Apply one frame addressed to this axis at time ``t``; returns the replies."""
        self._fed = t  # the vendor's watchdog is fed by any frame to the axis
        s = f.signals
        if f.remote:
            return self._reply(f.name)
        if f.name == "Set_Axis_State":
            self._request_state(int(s["Axis_Requested_State"]), t)
        elif f.name == "Set_Controller_Mode":
            try:
                self.control_mode, self.input_mode = ControlMode(s["Control_Mode"]), InputMode(s["Input_Mode"])
            except ValueError:
                _count(self.counters, "bad_value")
        elif f.name == "Set_Input_Vel":
            if self.state != AxisState.CLOSED_LOOP_CONTROL:
                self.errors |= odrive.error_bit(INPUT_REJECTED_ERROR)  # stays put, says so in its heartbeat
                _count(self.counters, "rejected_input")
            elif not math.isfinite(s["Input_Vel"]):
                _count(self.counters, "bad_value")
            else:
                self.input_vel = float(s["Input_Vel"])
        elif f.name == "Estop":
            self.disarm(odrive.error_bit("ESTOP_REQUESTED"))
        elif f.name == "Set_Absolute_Position":
            if math.isfinite(s["Position"]):
                self.pos = float(s["Position"])
            else:
                _count(self.counters, "bad_value")
        elif f.name == "Clear_Errors":  # a condition still present (persistent error) stays
            self.errors = self.disarm_reason = self.conditions
            self.procedure_result = ProcedureResult.SUCCESS
        else:
            _count(self.counters, "unsupported")
        return []

    def _request_state(self, requested: int, t: float) -> None:
        if requested == AxisState.IDLE:
            self._stop()
        elif requested == AxisState.CLOSED_LOOP_CONTROL:
            if self.errors:
                self.procedure_result = ProcedureResult.DISARMED
                return
            if self.state != AxisState.CLOSED_LOOP_CONTROL:
                self.state, self.input_vel = AxisState.CLOSED_LOOP_CONTROL, 0.0
            self.procedure_result = ProcedureResult.SUCCESS
            self._fed = t
        else:  # calibration and the rest are not simulated
            self.procedure_result = ProcedureResult.INVALID_STATE
            _count(self.counters, "unsupported")

    def _reply(self, name: str) -> list[can.Message]:
        if name == "Get_Encoder_Estimates":
            return [self.encoder_frame()]
        signals = self._get_signals(name)
        if signals is None:
            _count(self.counters, "unsupported")
            return []
        return [odrive.encode(name, self.node_id, **signals)]

    def _get_signals(self, name: str) -> dict | None:
        """The signals of a "Get" reply (DBC names), from the motor model; None: not a message we answer."""
        m = self.motor
        torque = m.torque(self.vel, self.accel) if self.state == AxisState.CLOSED_LOOP_CONTROL else 0.0
        iq = torque / m.torque_constant
        mech = torque * 2.0 * math.pi * self.vel
        elec = mech + m.copper_loss(iq)
        if name == "Get_Error":
            return {"Active_Errors": self.errors, "Disarm_Reason": self.disarm_reason}
        if name == "Get_Bus_Voltage_Current":
            return {"Bus_Voltage": self.bus_voltage, "Bus_Current": elec / self.bus_voltage}
        if name == "Get_Iq":
            return {"Iq_Setpoint": iq, "Iq_Measured": iq}
        if name == "Get_Torques":
            return {"Torque_Target": torque, "Torque_Estimate": torque}
        if name == "Get_Powers":
            return {"Electrical_Power": elec, "Mechanical_Power": mech}
        if name == "Get_Temperature":
            loss = m.copper_loss(iq)
            return {"FET_Temperature": m.ambient + m.fet_k_per_w * loss, "Motor_Temperature": m.ambient + m.motor_k_per_w * loss}
        if name == "Get_Version":
            return dict(FIRMWARE_VERSION)
        return None

    # --- faults -----------------------------------------------------------------------
    def disarm(self, error_bits: int) -> None:
        """An axis error: set it, record it as the disarm reason, drop to IDLE."""
        self.errors |= error_bits
        self.disarm_reason = error_bits
        self._stop()

    def inject_error(self, name: str, persistent: bool = False) -> None:
        """A fault as real hardware would have it (e.g. ``"DRV_FAULT"``): error + IDLE.
        ``persistent``: the condition stays (an undervolted DC bus), so Clear_Errors cannot clear it."""
        bit = odrive.error_bit(name)
        if persistent:
            self.conditions |= bit
        self.disarm(bit)

    def remove_condition(self, name: str) -> None:
        """The persistent condition is gone; the error stays until Clear_Errors."""
        self.conditions &= ~odrive.error_bit(name)

    def _stop(self) -> None:
        self.state, self.input_vel, self.vel = AxisState.IDLE, 0.0, 0.0

    # --- time -------------------------------------------------------------------------
    def advance(self, t: float) -> list[can.Message]:
        """Integrate to ``t`` (ramp, position, watchdog); returns the periodic frames due by then
        (at most one of each kind: a caller stepping coarsely gets the newest, not a burst)."""
        if self._t is None:
            self._t = self._next_hb = self._next_enc = self._fed = t
        out = []
        while self.all_samples and self._next_enc <= t + TIME_EPS:  # each estimate at its own time
            self._advance_to(self._next_enc)
            out.append(self.encoder_frame())
            out[-1].timestamp = self._next_enc  # when it was taken: a pair sends its axes' frames in time order
            self._next_enc += self.encoder_period
        self._advance_to(t)
        if not self.all_samples and t + TIME_EPS >= self._next_enc:
            out.append(self.encoder_frame())
            self._next_enc = _next_due(self._next_enc, self.encoder_period, t)
        if t + TIME_EPS >= self._next_hb:
            if not self.heartbeats_muted:
                out.append(self.heartbeat_frame())
            self._next_hb = _next_due(self._next_hb, self.heartbeat_period, t)
        return out

    def restart_timers(self, t: float) -> None:
        """The axis's clock is ``t`` from now on (a caller's clock changed hands: wall time to lock-step): the
        first heartbeat and estimate are due a period after ``t``, the watchdog counts from ``t``, nothing is
        integrated over the jump."""
        self._t = self._fed = t
        self._next_hb, self._next_enc = t + self.heartbeat_period, t + self.encoder_period

    def _advance_to(self, t: float) -> None:
        """Integrate to ``t``, the watchdog expiring on the way."""
        if t <= self._t:
            return
        expiry = self._fed + self.watchdog_timeout
        if self.watchdog_timeout > 0 and self.state == AxisState.CLOSED_LOOP_CONTROL and expiry < t:
            self._integrate(max(expiry, self._t))
            self.disarm(odrive.error_bit("WATCHDOG_TIMER_EXPIRED"))
        self._integrate(t)

    def _integrate(self, t: float) -> None:
        dt = t - self._t
        self._t = t
        if dt <= 0:
            return
        v_before = self.vel
        self._ramp(dt)
        self.accel = (self.vel - v_before) / dt

    def _ramp(self, dt: float) -> None:
        target = self.input_vel if (self.state == AxisState.CLOSED_LOOP_CONTROL
                                    and self.control_mode == ControlMode.VELOCITY_CONTROL) else 0.0
        v0 = self.vel
        if self.input_mode != InputMode.VEL_RAMP or self.vel_ramp_rate <= 0:
            self.vel = target
            self.pos += target * dt
            return
        t_reach = abs(target - v0) / self.vel_ramp_rate
        if t_reach >= dt:
            self.vel = v0 + math.copysign(self.vel_ramp_rate * dt, target - v0)
            self.pos += 0.5 * (v0 + self.vel) * dt
        else:
            self.vel = target
            self.pos += 0.5 * (v0 + target) * t_reach + target * (dt - t_reach)

    # --- frames out -------------------------------------------------------------------
    def heartbeat_frame(self) -> can.Message:
        return odrive.encode("Heartbeat", self.node_id, Axis_Error=self.errors, Axis_State=self.state,
                             Procedure_Result=self.procedure_result, Trajectory_Done_Flag=1)

    def encoder_frame(self) -> can.Message:
        return odrive.encode("Get_Encoder_Estimates", self.node_id, Pos_Estimate=self.pos, Vel_Estimate=self.vel)


def _next_due(due: float, period: float, t: float) -> float:
    due += period
    return due if due > t + TIME_EPS else t + period


class ODrivePair:
    """Simulated ODrive axes (by default nodes 0 and 1: left and right wheel) on one CAN bus.

    ``bus``: any ``can.BusABC`` (a ``virtual`` bus, an ``SlcanPtyBus``, a real adapter).
    ``axis_params`` go to every ``SimAxis`` (``vel_ramp_rate``, ``watchdog_timeout``...).
    The pair neither opens nor shuts down the bus.
    """

    def __init__(self, bus: can.BusABC, node_ids: tuple[int, ...] = (0, 1), *,
                 clock: Callable[[], float] = time.monotonic, **axis_params):
        self.bus = bus
        self.axes = {n: SimAxis(n, **axis_params) for n in node_ids}
        self.counters: dict[str, int] = {}
        self._clock = clock
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- lock-step ----------------------------------------------------------------------
    def step(self, t_now: float) -> None:
        """Handle every frame received so far, advance the axes to ``t_now``, send what is due.

        Frames received since the last step take effect at its start (a zero-order hold:
        a lock-step world's command acts over the whole next step).
        """
        self.receive(t_now)
        self.send(self.advance(t_now))

    def receive(self, t_now: float) -> None:
        """Handle every frame received so far, at ``t_now`` (replies go out at once)."""
        with self._lock:
            while (msg := self.bus.recv(0.0)) is not None:
                self._handle(msg, t_now)

    def advance(self, t_now: float) -> list[can.Message]:
        """Advance the axes to ``t_now``; the periodic frames due by then, for ``send`` (a world sends
        them once it has moved the body, so they describe the body at ``t_now``)."""
        with self._lock:
            frames = [m for axis in self.axes.values() for m in axis.advance(t_now)]
            if any(axis.all_samples for axis in self.axes.values()):  # as on a bus: in the order they were taken
                frames.sort(key=lambda m: m.timestamp if m.timestamp else t_now)
            return frames

    def send(self, msgs: list[can.Message]) -> None:
        with self._lock:
            self._send_all(msgs)

    def _handle(self, msg: can.Message, t: float) -> None:
        try:
            f = odrive.decode(msg, self.axes)
        except odrive.ProtocolError as e:
            return _count(self.counters, e.kind)
        axis = self.axes[f.node_id]
        _count(self.counters, "rx")
        self._send_all(axis.handle(f, t))

    def _send_all(self, msgs: list[can.Message]) -> None:
        for m in msgs:
            try:
                self.bus.send(m)
                _count(self.counters, "tx")
            except can.CanError:
                _count(self.counters, "tx_error")

    # --- wall time ----------------------------------------------------------------------
    def run_realtime(self, poll: float = 0.001) -> "ODrivePair":
        """Step on wall time from a thread; a frame is handled as soon as it arrives."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, args=(poll,), name="odrive-sim", daemon=True)
            self._thread.start()
        return self

    def _run(self, poll: float) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(poll)
            except can.CanError:
                _count(self.counters, "rx_error")
                self._stop.wait(poll)
                continue
            now = self._clock()
            if msg is not None:
                with self._lock:
                    self._handle(msg, now)
            self.step(now)

    def stop(self) -> None:
        """Stop the realtime thread (a powered-off device: nothing more on the bus)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None

    def __enter__(self) -> "ODrivePair":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # --- for the world and for tests ----------------------------------------------------
    def restart_timers(self, t: float) -> None:
        """Every axis's timers start again at ``t`` (``SimAxis.restart_timers``)."""
        with self._lock:
            for axis in self.axes.values():
                axis.restart_timers(t)

    def heartbeats(self) -> list[can.Message]:
        """Every axis's heartbeat now (none from a muted one), out of its schedule (a caller standing still)."""
        with self._lock:
            return [a.heartbeat_frame() for a in self.axes.values() if not a.heartbeats_muted]

    def vel(self, node_id: int) -> float:
        """Motor velocity [rev/s] of an axis, as its encoder reports it."""
        return self.axes[node_id].vel

    def wheel_omega(self, node_id: int, gear_ratio: float = 1.0, direction: int = 1) -> float:
        """Wheel angular velocity [rad/s] (positive: forward) of an axis through its gear and mounting."""
        return self.axes[node_id].vel * 2.0 * math.pi / gear_ratio * direction

    def mute_heartbeats(self, muted: bool = True) -> None:
        with self._lock:
            for axis in self.axes.values():
                axis.heartbeats_muted = muted

    def inject_error(self, node_id: int, name: str, persistent: bool = False) -> None:
        with self._lock:
            self.axes[node_id].inject_error(name, persistent)


TX_BACKLOG = 8192
"""[bytes] adapter -> host data held while the host does not read (a USB-CAN adapter's FIFO, a few hundred frames)."""


class SlcanPtyBus(can.BusABC):
    """The adapter end of an slcan (Lawicel) USB-CAN adapter, on a pseudo-terminal.

    Holds the pty master and speaks the ASCII protocol python-can's ``slcan`` interface
    sends on the slave (``slave_path``): ``O``/``L`` open, ``C`` close, ``S0``..``S8``
    bitrate, ``s`` BTR, ``V``/``v`` version, ``N`` serial number, ``F`` status, ``Z``
    timestamps; acks ``\\r``, refusals ``\\a``; frames ``t``/``T``/``r``/``R`` both ways
    (acked ``z\\r``/``Z\\r``). While the channel is closed no frames pass. Bad ASCII is
    counted in ``counters`` and answered ``\\a``, never raised.
    """

    _BITRATES = {"0": 10_000, "1": 20_000, "2": 50_000, "3": 100_000, "4": 125_000, "5": 250_000,
                 "6": 500_000, "7": 750_000, "8": 1_000_000, "9": 83_300}
    VERSION = "V1013"
    SERIAL = "NSIM1"
    MAX_LINE = 64  # longest valid line: T + 8 id + 1 dlc + 16 data

    def __init__(self, channel: str | None = None, **kwargs):
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo before the host's pyserial sets raw itself
        os.set_blocking(self._master, False)
        self.slave_path = os.ttyname(self._slave)
        self.channel_open = False
        self.bitrate: int | None = None
        self.counters: dict[str, int] = {}
        self._buffer = bytearray()
        self._tx = bytearray()  # adapter -> host bytes the pty has not taken yet (whole frames but the first)
        self._tx_partial = False  # the first frame in ``_tx`` is partly on the wire already
        self._frames: deque[can.Message] = deque()
        super().__init__(channel=self.slave_path, **kwargs)
        self.channel_info = f"slcan adapter on {self.slave_path}"

    # --- toward the host ----------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self.channel_open:
            return _count(self.counters, "dropped_closed")
        if msg.is_error_frame or msg.is_fd:
            return _count(self.counters, "dropped_unsupported")
        kind = ("R" if msg.is_remote_frame else "T") if msg.is_extended_id else ("r" if msg.is_remote_frame else "t")
        ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
        data = "" if msg.is_remote_frame else bytes(msg.data).hex().upper()
        self._write(f"{kind}{ident}{msg.dlc:d}{data}\r")

    def _write(self, text: str) -> None:
        """Frames to the host, never a part of one: what the pty does not take now waits, and a host
        that stops reading loses whole frames (counted ``overrun``), as an adapter's full FIFO does."""
        self._tx += text.encode("ascii")
        try:
            sent = os.write(self._master, self._tx)
        except BlockingIOError:
            sent = 0
        except OSError as e:
            if e.errno != errno.EIO:
                raise can.CanOperationError(f"slcan pty write failed: {e}") from e
            sent = 0
        if sent:
            self._tx_partial = self._tx[sent - 1:sent] != b"\r"
        del self._tx[:sent]
        self._tx_partial = self._tx_partial and bool(self._tx)
        if len(self._tx) > TX_BACKLOG:
            keep = self._tx.find(b"\r") + 1 if self._tx_partial else 0  # finish the frame already begun
            for _ in range(self._tx.count(b"\r", keep)):
                _count(self.counters, "overrun")
            del self._tx[keep:]

    # --- from the host ------------------------------------------------------------------
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._frames:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select([self._master], [], [], wait)
            if ready:
                try:
                    chunk = os.read(self._master, 4096)
                except (BlockingIOError, InterruptedError):
                    chunk = b""
                except OSError as e:  # EIO: no slave open (cannot happen while we hold one)
                    raise can.CanOperationError(f"slcan pty read failed: {e}") from e
                self._feed(chunk)
            if not self._frames and deadline is not None and time.monotonic() >= deadline:
                return None, False
        return self._frames.popleft(), False

    def _feed(self, chunk: bytes) -> None:
        self._buffer.extend(chunk)
        while True:
            end = self._buffer.find(b"\r")
            if end < 0:
                if len(self._buffer) > self.MAX_LINE:
                    _count(self.counters, "bad_ascii")
                    self._buffer.clear()
                return
            line = bytes(self._buffer[:end]).lstrip(b"\n")
            del self._buffer[: end + 1]
            self._command(line)

    def _command(self, raw: bytes) -> None:
        try:
            line = raw.decode("ascii")
        except UnicodeDecodeError:
            line = None
        if line is None or not line.isprintable():
            return self._refuse("bad_ascii")
        head, arg = line[:1], line[1:]
        if head in "tTrR" and line:
            return self._frame(line)
        if head == "":
            return self._write("\r")
        if head in ("O", "L") and not arg:
            if self.channel_open:
                return self._refuse("nak")
            self.channel_open = True
            return self._write("\r")
        if head == "C" and not arg:
            if not self.channel_open:
                return self._refuse("nak")
            self.channel_open = False
            return self._write("\r")
        if head == "S" and arg in self._BITRATES:
            if self.channel_open:
                return self._refuse("nak")
            self.bitrate = self._BITRATES[arg]
            return self._write("\r")
        if head == "s" and len(arg) == 4 and _is_hex(arg):
            return self._refuse("nak") if self.channel_open else self._write("\r")
        if line in ("V", "v"):
            return self._write(f"{self.VERSION if head == 'V' else 'vSIM'}\r")
        if line == "N":
            return self._write(f"{self.SERIAL}\r")
        if line == "F":
            return self._write("F00\r")
        if head == "Z" and arg in ("0", "1"):
            return self._write("\r")
        return self._refuse("bad_ascii")

    def _frame(self, line: str) -> None:
        kind = line[0]
        n_id = 8 if kind in "TR" else 3
        ident, dlc_s, data = line[1:1 + n_id], line[1 + n_id:2 + n_id], line[2 + n_id:]
        if len(ident) != n_id or not _is_hex(ident) or not dlc_s.isdigit() or int(dlc_s) > 8:
            return self._refuse("bad_ascii")
        dlc, remote = int(dlc_s), kind in "rR"
        if (remote and data) or (not remote and (len(data) != 2 * dlc or not _is_hex(data))):
            return self._refuse("bad_ascii")
        arb = int(ident, 16)
        if arb > (0x1FFFFFFF if kind in "TR" else 0x7FF):
            return self._refuse("bad_ascii")
        if not self.channel_open:
            return self._refuse("closed")
        self._frames.append(can.Message(arbitration_id=arb, is_extended_id=kind in "TR", is_remote_frame=remote,
                                        dlc=dlc, data=None if remote else bytes.fromhex(data),
                                        timestamp=time.time(), channel=self.slave_path))
        _count(self.counters, "frames")
        self._write("Z\r" if kind in "TR" else "z\r")

    def _refuse(self, kind: str) -> None:
        _count(self.counters, kind)
        self._write("\a")

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


def _is_hex(s: str) -> bool:
    return all(c in "0123456789abcdefABCDEF" for c in s)


__all__ = ["FIRMWARE_VERSION", "INPUT_REJECTED_ERROR", "MotorModel", "ODrivePair", "SimAxis", "SlcanPtyBus"]
