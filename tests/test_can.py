"""The CAN driver (two ODrive axes, CANSimple 0.6) and the simulated ODrive pair and slcan adapter.

The wire is checked with cantools on the DBC itself (not with the driver's own helpers); the
driver runs against the simulated pair on python-can ``virtual`` buses and, through
python-can's real ``slcan`` interface, on a real pseudo-terminal.
"""

from __future__ import annotations

import itertools
import math
import os
import random
import select
import threading
import time

import can
import cantools
import pytest

from conftest import wait_for
from stack.drivers import DriverError, DriverLimits
from stack.drivers import odrive
from stack.drivers.can import CanConfig, CanDriver
from stack.drivers.testing import FakeClock, settle
from stack.sim_bridge.odrive_sim import INPUT_REJECTED_ERROR, ODrivePair, SimAxis, SlcanPtyBus

DBC = cantools.database.load_file(os.path.join(os.path.dirname(odrive.__file__), odrive.DBC_FILE))
LIMITS = DriverLimits(v_max=1.0, w_max=2.0, cmd_timeout=5.0)
CFG = CanConfig(interface="virtual", wheel_radius=0.1, track_width=0.4, gear_ratio=2.0, open_timeout=1.0)
RAMP = 40.0  # [rev/s^2] sim ramp: fast, so tests need not wait long
_channels = itertools.count()


def dbc_decode(msg: can.Message) -> tuple[str, dict]:
    """Decode a frame with the DBC alone (nodes 0..7 are in it): (message name, signals with choice names)."""
    m = DBC.get_message_by_frame_id(msg.arbitration_id)
    return m.name, (m.decode(bytes(msg.data), decode_choices=True) if m.signals else {})


def host_frames(frames: list[can.Message]) -> list[tuple[str, dict]]:
    """The frames a host (the DBC's ``Master``) sent, decoded by the DBC."""
    out = []
    for f in frames:
        m = DBC.get_message_by_frame_id(f.arbitration_id)
        if "Master" in (m.senders or []) and not f.is_remote_frame:
            out.append(dbc_decode(f))
    return out


class Rig:
    """A virtual CAN bus with the simulated pair (wall time), a driver and a sniffer recording every frame."""

    def __init__(self, clock=time.monotonic, **cfg):
        self.channel = f"odrive-test-{next(_channels)}-{os.getpid()}"
        self.sim_bus = can.Bus(interface="virtual", channel=self.channel)
        self.sniffer = can.Bus(interface="virtual", channel=self.channel)
        self.frames: list[can.Message] = []
        self.notifier = can.Notifier(self.sniffer, [self.frames.append], timeout=0.02)
        self.pair = ODrivePair(self.sim_bus, vel_ramp_rate=RAMP)
        self.cfg = CanConfig(**{**CFG.__dict__, "channel": self.channel, **cfg})
        self.driver = CanDriver(7, LIMITS, self.cfg, clock=clock)

    def start(self) -> "Rig":
        self.pair.run_realtime()
        self.driver.open()
        return self

    def close(self):
        self.driver.close()
        self.pair.stop()
        self.notifier.stop()
        while (m := self.sniffer.recv(0.0)) is not None:  # what the notifier had not taken yet
            self.frames.append(m)
        self.sniffer.shutdown()
        self.sim_bus.shutdown()

    def reached(self) -> bool:
        """The newest command is the left axis's input (it went over the bus)."""
        left = self.cfg.motor_velocities(*self.driver.last_sent)[0]
        return self.pair.axes[self.cfg.node_left].input_vel == pytest.approx(left)

    def wheel(self, node: int) -> float:
        """Wheel rad/s, positive forward, from the sim's motor velocity."""
        direction = self.cfg.direction_left if node == self.cfg.node_left else self.cfg.direction_right
        return self.pair.wheel_omega(node, self.cfg.gear_ratio, direction)


@pytest.fixture
def rig():
    r = Rig().start()
    yield r
    r.close()


# --- protocol -------------------------------------------------------------------------------
def test_set_input_vel_matches_the_vendor_example():
    msg = odrive.encode("Set_Input_Vel", 1, Input_Vel=1.5)
    assert msg.arbitration_id == 0x02D and not msg.is_extended_id
    assert bytes(msg.data) == bytes.fromhex("0000c03f00000000")
    assert dbc_decode(msg) == ("Axis1_Set_Input_Vel", {"Input_Vel": 1.5, "Input_Torque_FF": 0.0})
    assert odrive.arbitration_id(63, 0x1F) == 0x7FF and odrive.split_id(0x7FF) == (63, 0x1F)
    with pytest.raises(ValueError):
        odrive.arbitration_id(64, 1)


def test_constants_and_error_names_come_from_the_dbc():
    for enum, (message, signal) in odrive.ENUM_SIGNALS.items():
        choices = {int(v): str(n) for v, n in DBC.get_message_by_name(f"Axis0_{message}")
                   .get_signal_by_name(signal).choices.items()}
        for member in enum:
            assert choices[member.value] == member.name, (enum, member)
    bits = odrive.error_bit("WATCHDOG_TIMER_EXPIRED") | odrive.error_bit("DRV_FAULT") | 1 << 31
    assert bits & 0x7FFFFFFF == 0x01000020
    assert odrive.error_names(bits) == ["DRV_FAULT", "WATCHDOG_TIMER_EXPIRED", "0x80000000"]
    assert odrive.error_text(0) == "NONE"
    # a node beyond the DBC's 0..7 still encodes (templates + computed id)
    assert odrive.decode(odrive.encode("Heartbeat", 40, Axis_State=8)).node_id == 40


def test_decode_rejects_what_is_not_cansimple():
    kinds = []
    for msg in (can.Message(arbitration_id=0x001, data=b"\x00" * 4, is_extended_id=False),
                can.Message(arbitration_id=0x008, data=b"", is_extended_id=False),
                can.Message(arbitration_id=0x1234567, data=b"", is_extended_id=True),
                can.Message(is_error_frame=True)):
        with pytest.raises(odrive.ProtocolError) as e:
            odrive.decode(msg)
        kinds.append(e.value.kind)
    assert kinds == ["bad_dlc", "unknown_cmd", "extended_id", "error_frame"]


# --- kinematics -----------------------------------------------------------------------------
def test_kinematics_signs_and_round_trip():
    cfg = CanConfig(wheel_radius=0.1, track_width=0.4, gear_ratio=2.0)
    left, right = cfg.motor_velocities(0.5, 0.0)
    assert left == pytest.approx(0.5 / (2 * math.pi * 0.1) * 2.0) and right == pytest.approx(-left)  # mirrored right
    left, right = cfg.motor_velocities(0.0, 1.0)  # turn left: right wheel forward, left back
    assert left < 0 and right * cfg.direction_right > 0
    assert cfg.body_velocity(*cfg.motor_velocities(0.3, -0.7)) == pytest.approx((0.3, -0.7))


def test_config_is_checked_and_settings_override_it():
    with pytest.raises(ValueError, match="direction"):
        CanConfig(direction_right=0)
    with pytest.raises(ValueError, match="both wheels"):
        CanConfig(node_left=3, node_right=3)
    with pytest.raises(ValueError, match="unknown settings"):
        CanDriver(1, LIMITS, bogus=1)
    d = CanDriver(1, LIMITS, CFG, node_left=4, node_right=5, session=None, keys=None, on_malformed=None)
    assert (d.config.node_left, d.config.node_right, d.config.wheel_radius) == (4, 5, 0.1)


# --- the simulated ODrive, in lock-step time ------------------------------------------------
class LockStep:
    """The pair on a virtual bus, stepped by the test's clock; the host end is a second bus."""

    def __init__(self, **axis):
        ch = f"odrive-lockstep-{next(_channels)}-{os.getpid()}"
        self.sim_bus = can.Bus(interface="virtual", channel=ch)
        self.host = can.Bus(interface="virtual", channel=ch)
        self.pair = ODrivePair(self.sim_bus, **axis)
        self.t = 0.0

    def send(self, msg: can.Message):
        self.host.send(msg)

    def step_to(self, t: float) -> list[can.Message]:
        self.pair.step(t)
        self.t = t
        out = []
        while (m := self.host.recv(0.0)) is not None:
            out.append(m)
        return out

    def heartbeat(self, frames, node: int) -> dict:
        hb = [dbc_decode(f)[1] for f in frames if f.arbitration_id == odrive.arbitration_id(node, 1)]
        assert hb, "no heartbeat"
        return hb[-1]

    def close(self):
        self.host.shutdown()
        self.sim_bus.shutdown()


@pytest.fixture
def lockstep():
    ls = LockStep(vel_ramp_rate=10.0)
    yield ls
    ls.close()


def test_sim_rejects_velocity_before_closed_loop(lockstep):
    ls = lockstep
    ls.step_to(0.0)
    ls.send(odrive.encode("Set_Input_Vel", 0, Input_Vel=3.0))
    frames = ls.step_to(0.5)
    hb = ls.heartbeat(frames, 0)
    assert hb["Axis_State"] == "IDLE" and hb["Axis_Error"] == INPUT_REJECTED_ERROR
    assert ls.pair.vel(0) == 0.0 and ls.pair.axes[0].pos == 0.0
    assert ls.heartbeat(frames, 1)["Axis_Error"] == "NONE"  # the other axis is untouched
    # closed loop is refused while the error stands; Clear_Errors lets it in
    ls.send(odrive.encode("Set_Axis_State", 0, Axis_Requested_State=8))
    ls.step_to(0.6)
    assert ls.pair.axes[0].state == odrive.AxisState.IDLE
    assert ls.pair.axes[0].procedure_result == odrive.ProcedureResult.DISARMED
    for msg in (odrive.encode("Clear_Errors", 0), odrive.encode("Set_Controller_Mode", 0, Control_Mode=2, Input_Mode=2),
                odrive.encode("Set_Axis_State", 0, Axis_Requested_State=8), odrive.encode("Set_Input_Vel", 0, Input_Vel=3.0)):
        ls.send(msg)
    ls.step_to(0.7)
    assert ls.pair.vel(0) == pytest.approx(1.0)  # VEL_RAMP: 10 rev/s^2 for 0.1 s
    ls.send(odrive.encode("Set_Input_Vel", 0, Input_Vel=3.0))
    frames = ls.step_to(1.0)
    assert ls.pair.vel(0) == pytest.approx(3.0)
    assert ls.pair.axes[0].pos == pytest.approx(0.05 + 0.5 * (1.0 + 3.0) * 0.2 + 3.0 * 0.1)  # ramp, then cruise
    hb = ls.heartbeat(frames, 0)
    assert (hb["Axis_State"], hb["Axis_Error"]) == ("CLOSED_LOOP_CONTROL", "NONE")


def test_sim_watchdog_estop_get_error_and_rtr(lockstep):
    ls = lockstep
    ls.step_to(0.0)
    for msg in (odrive.encode("Set_Controller_Mode", 1, Control_Mode=2, Input_Mode=1),
                odrive.encode("Set_Axis_State", 1, Axis_Requested_State=8), odrive.encode("Set_Input_Vel", 1, Input_Vel=-2.0)):
        ls.send(msg)
    ls.step_to(0.4)
    assert ls.pair.vel(1) == -2.0  # PASSTHROUGH
    ls.send(odrive.request("Get_Encoder_Estimates", 1))
    frames = ls.step_to(0.4)  # an RTR is answered in the same step
    enc = [dbc_decode(f)[1] for f in frames if f.arbitration_id == odrive.arbitration_id(1, 9)]
    assert enc[-1]["Vel_Estimate"] == -2.0 and enc[-1]["Pos_Estimate"] == pytest.approx(-0.8)
    frames = ls.step_to(1.0)  # last frame at 0.4 s: the 0.5 s watchdog expires at 0.9 s
    hb = ls.heartbeat(frames, 1)
    assert (hb["Axis_State"], hb["Axis_Error"]) == ("IDLE", "WATCHDOG_TIMER_EXPIRED")
    assert ls.pair.vel(1) == 0.0 and ls.pair.axes[1].pos == pytest.approx(-1.8)
    ls.send(odrive.request("Get_Error", 1))
    err = [dbc_decode(f)[1] for f in ls.step_to(1.0) if f.arbitration_id == odrive.arbitration_id(1, 3)]
    assert err == [{"Active_Errors": "WATCHDOG_TIMER_EXPIRED", "Disarm_Reason": "WATCHDOG_TIMER_EXPIRED"}]
    for msg in (odrive.encode("Clear_Errors", 1), odrive.encode("Set_Axis_State", 1, Axis_Requested_State=8)):
        ls.send(msg)
    ls.step_to(1.1)
    assert ls.pair.axes[1].state == odrive.AxisState.CLOSED_LOOP_CONTROL
    ls.send(odrive.encode("Estop", 1))
    hb = ls.heartbeat(ls.step_to(1.3), 1)
    assert (hb["Axis_State"], hb["Axis_Error"]) == ("IDLE", "ESTOP_REQUESTED")


@pytest.mark.parametrize("dt, encoders", [(1 / 256, 65), (1 / 32, 33)])
def test_sim_periodic_frames_follow_the_callers_time(dt, encoders):
    """Periods and steps exact in binary: heartbeats every 1/8 s, encoder every 1/64 s; a step
    coarser than a period gets one (the newest) frame, not a burst."""
    ls = LockStep(heartbeat_period=1 / 8, encoder_period=1 / 64)
    try:
        frames = []
        for k in range(round(1 / dt) + 1):  # 0 .. 1 s
            frames += ls.step_to(k * dt)
        ids = [f.arbitration_id for f in frames]
        for node in (0, 1):
            assert ids.count(odrive.arbitration_id(node, 1)) == 9
            assert ids.count(odrive.arbitration_id(node, 9)) == encoders
        ls.pair.mute_heartbeats()
        assert odrive.arbitration_id(0, 1) not in [f.arbitration_id for f in ls.step_to(2.0)]
    finally:
        ls.close()


def test_sim_default_periods_are_the_vendors(lockstep):
    frames = []
    for k in range(1001):  # 1 s in 1 ms steps
        frames += lockstep.step_to(k / 1000)
    ids = [f.arbitration_id for f in frames]
    assert ids.count(0x001) in (10, 11) and ids.count(0x009) in (100, 101)


# --- driver + simulated pair on a virtual bus ------------------------------------------------
def test_driver_frames_decode_to_the_intended_signals():
    r = Rig().start()
    try:
        r.driver.command(0.5, 0.0)
        assert wait_for(r.reached, 1.0)
    finally:
        r.close()
    sent = host_frames(r.frames)
    k = 0.5 / (2 * math.pi * 0.1) * 2.0  # wheel rev/s times the gear: 1.5915 rev/s
    start = [(n, s) for n, s in sent[:6]]
    assert start == [
        ("Axis0_Clear_Errors", {"Identify": 0}),
        ("Axis0_Set_Controller_Mode", {"Control_Mode": "VELOCITY_CONTROL", "Input_Mode": "VEL_RAMP"}),
        ("Axis0_Set_Axis_State", {"Axis_Requested_State": "CLOSED_LOOP_CONTROL"}),
        ("Axis1_Clear_Errors", {"Identify": 0}),
        ("Axis1_Set_Controller_Mode", {"Control_Mode": "VELOCITY_CONTROL", "Input_Mode": "VEL_RAMP"}),
        ("Axis1_Set_Axis_State", {"Axis_Requested_State": "CLOSED_LOOP_CONTROL"}),
    ]
    zero = {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}
    assert sent[6:8] == [("Axis0_Set_Input_Vel", zero), ("Axis1_Set_Input_Vel", zero)]  # in closed loop: fed at once
    moving = [(n, s) for n, s in sent[8:] if s != zero]
    name, s = moving[0]
    assert name == "Axis0_Set_Input_Vel" and s["Input_Vel"] == pytest.approx(k, rel=1e-6) and s["Input_Torque_FF"] == 0
    name, s = moving[1]
    assert name == "Axis1_Set_Input_Vel" and s["Input_Vel"] == pytest.approx(-k, rel=1e-6)  # mirrored right motor
    assert sent[-4:] == [("Axis0_Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}),
                         ("Axis1_Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}),
                         ("Axis0_Set_Axis_State", {"Axis_Requested_State": "IDLE"}),
                         ("Axis1_Set_Axis_State", {"Axis_Requested_State": "IDLE"})]
    assert {n for n, _ in sent} <= {"Axis0_Clear_Errors", "Axis0_Set_Controller_Mode", "Axis0_Set_Axis_State",
                                    "Axis0_Set_Input_Vel", "Axis1_Clear_Errors", "Axis1_Set_Controller_Mode",
                                    "Axis1_Set_Axis_State", "Axis1_Set_Input_Vel"}


def test_commands_move_the_wheels_and_odometry_follows(rig):
    assert rig.driver.fault is None
    rig.driver.command(0.4, 0.0)  # forward: both wheels forward, equally
    assert wait_for(lambda: abs(rig.wheel(0) - 4.0) < 1e-5 and abs(rig.wheel(1) - 4.0) < 1e-5, 1.0)  # 0.4 m/s / 0.1 m
    assert wait_for(lambda: (o := rig.driver.read()) is not None and o.v == pytest.approx(0.4, abs=1e-4), 1.0)
    odo = rig.driver.read()
    assert odo.w == pytest.approx(0.0, abs=1e-4)
    rig.driver.command(0.2, 1.0)  # turn left: the right wheel faster
    assert wait_for(lambda: abs(rig.wheel(0)) < 1e-3, 1.0)  # left slows to 0 rad/s
    assert rig.wheel(1) == pytest.approx(4.0)  # right stays at 4 rad/s: (0.2 + 1.0 * 0.2) / 0.1
    turning = (pytest.approx(0.2, abs=1e-4), pytest.approx(1.0, abs=1e-4))
    assert wait_for(lambda: (rig.driver.read().v, rig.driver.read().w) == turning, 1.0), rig.driver.read()
    odo = rig.driver.read()
    assert abs(time.time() - odo.stamp) < 0.1
    rig.driver.command(-0.3, 0.0)  # backwards, and the keepalive holds it past the axis watchdog
    time.sleep(0.8)
    assert rig.driver.fault is None and rig.pair.axes[0].state == odrive.AxisState.CLOSED_LOOP_CONTROL
    assert rig.driver.read().v == pytest.approx(-0.3, abs=1e-4)


@pytest.mark.parametrize("failure", ["killed", "heartbeats muted"])
def test_lost_device_is_a_named_fault_with_estop(failure):
    """The heartbeat timeout runs on the driver's clock (fake here: it stands still while the last
    heartbeats arrive, so only the test's steps age them); the keepalive follows the wall and keeps the
    axes' own watchdogs fed meanwhile."""
    clock = FakeClock()
    rig = Rig(clock=clock).start()
    try:
        rig.driver.command(0.3, 0.0)
        assert wait_for(rig.reached, 1.0)
        n0 = len(rig.frames)
        if failure == "killed":
            rig.pair.stop()
        else:
            rig.pair.mute_heartbeats()
        assert settle(lambda: rig.driver.counters["heartbeat"])  # what was on the way has arrived
        clock.advance(0.25)  # heartbeat_timeout is 0.3 s
        rig.driver.supervise_once()
        assert rig.driver.fault is None
        clock.advance(0.125)
        rig.driver.supervise_once()
        fault = rig.driver.fault
        assert fault and "\n" not in fault, fault
        assert "left axis (node 0): no heartbeat for 0.38 s; right axis (node 1): no heartbeat for 0.38 s" == fault
        for node in (0, 1):
            assert wait_for(lambda: (f"Axis{node}_Estop", {}) in host_frames(rig.frames[n0:]), 1.0)
        tail = host_frames(rig.frames[n0:])
        for node in (0, 1):
            assert (f"Axis{node}_Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}) in tail
        assert rig.driver.command(0.5, 0.0) == (0.0, 0.0)  # a faulted driver sends no motion
        if failure == "heartbeats muted":  # the device itself obeyed the Estop
            assert wait_for(lambda: rig.pair.axes[0].state == rig.pair.axes[1].state == odrive.AxisState.IDLE, 1.0)
        assert rig.driver.counters["estop"] == 2
    finally:
        rig.close()


def test_the_control_step_itself_trips_a_stale_heartbeat():
    """A lock-step agent's clock jumps a step at a time while its threads may be starved (a loaded
    machine): ``command()`` checks the heartbeats on that clock itself, so a stale device stops the robot
    on the first step it is stale, whatever the supervisor thread is doing. Here only the control thread
    sees time pass; the supervisor and the receiver see it stand still, as a starved thread would."""
    control = threading.current_thread()
    now = [0.0]
    r = Rig()
    r.driver = CanDriver(7, LIMITS, r.cfg, clock=lambda: now[0] if threading.current_thread() is control else 0.0)
    r.start()
    try:
        assert r.driver.command(0.3, 0.0) == (0.3, 0.0)
        r.pair.mute_heartbeats()
        now[0] = 0.25  # within heartbeat_timeout (0.3 s) of the last heartbeat: still fine
        assert r.driver.command(0.3, 0.0) == (0.3, 0.0) and r.driver.fault is None
        now[0] = 0.35
        assert r.driver.command(0.3, 0.0) == (0.0, 0.0)  # this very step: zero, and the fault says why
        assert "no heartbeat for 0.35 s" in r.driver.fault
        assert wait_for(lambda: r.pair.axes[0].state == r.pair.axes[1].state == odrive.AxisState.IDLE, 1.0)
    finally:
        r.close()


def test_axis_error_is_a_fault_naming_the_decoded_error(rig):
    rig.driver.command(0.3, 0.0)
    assert wait_for(rig.reached, 1.0)
    rig.pair.inject_error(1, "DRV_FAULT")
    fault = wait_for(lambda: rig.driver.fault, 0.5)
    assert fault and fault.startswith("right axis (node 1): axis error DRV_FAULT"), fault
    assert wait_for(lambda: rig.driver.counters.get("estop") == 2, 0.5), rig.driver.counters  # sent just after the fault is set


def test_open_fails_naming_the_axis_and_reason():
    ch = f"odrive-test-{next(_channels)}-{os.getpid()}"
    bus = can.Bus(interface="virtual", channel=ch)
    pair = ODrivePair(bus, node_ids=(0,)).run_realtime()  # only the left axis is there
    d = CanDriver(1, LIMITS, CFG, channel=ch, open_timeout=0.3)
    try:
        with pytest.raises(DriverError, match=r"right axis \(node 1\): no heartbeat") as e:
            d.open()
        assert "left axis" not in str(e.value) and "\n" not in str(e.value)
        pair.inject_error(0, "DC_BUS_UNDER_VOLTAGE", persistent=True)  # Clear_Errors cannot clear it
        pair2 = ODrivePair(can.Bus(interface="virtual", channel=ch), node_ids=(1,)).run_realtime()
        try:
            with pytest.raises(DriverError, match=r"left axis \(node 0\): state IDLE, error DC_BUS_UNDER_VOLTAGE"):
                d.open()
        finally:
            pair2.stop()
            pair2.bus.shutdown()
    finally:
        pair.stop()
        bus.shutdown()


def test_an_adapter_that_cannot_send_is_a_one_line_open_error():
    bus = can.Bus(interface="virtual", channel=f"odrive-test-{next(_channels)}-{os.getpid()}")

    def refuse(msg, timeout=None):
        raise can.CanOperationError("Could not write to serial device")

    bus.send = refuse
    try:
        with pytest.raises(DriverError, match=r"^can driver 1: cannot start the axes on .*: Could not write to serial "
                                              r"device$"):
            CanDriver(1, LIMITS, CFG, bus=bus).open()
    finally:
        bus.shutdown()


def test_malformed_traffic_is_counted_and_ignored(rig):
    rig.driver.command(0.2, 0.0)
    assert wait_for(lambda: rig.driver.read() is not None and rig.driver.read().v == pytest.approx(0.2, abs=1e-3), 1.0)
    rogue = can.Bus(interface="virtual", channel=rig.channel)
    rng = random.Random(5)
    sent = {"bad_dlc": 0, "unknown_cmd": 0, "other_node": 0, "extended_id": 0, "bad_value": 0, "error_frame": 0}
    try:
        for _ in range(10):
            rogue.send(can.Message(arbitration_id=0x001, data=b"\x00\x00\x00\x00", is_extended_id=False))  # short heartbeat
            rogue.send(can.Message(arbitration_id=0x029, data=bytes(3), is_extended_id=False))  # short encoder
            sent["bad_dlc"] += 2
            rogue.send(can.Message(arbitration_id=rng.choice([0x008, 0x00A, 0x010, 0x01E, 0x028, 0x03E]),
                                   data=bytes(8), is_extended_id=False))
            sent["unknown_cmd"] += 1
            rogue.send(can.Message(arbitration_id=rng.randrange(2 << 5, 0x800), is_extended_id=False,
                                   data=rng.randbytes(rng.randrange(9))))  # garbage from other nodes
            sent["other_node"] += 1
            rogue.send(can.Message(arbitration_id=rng.randrange(1 << 29), is_extended_id=True, data=rng.randbytes(8)))
            sent["extended_id"] += 1
            rogue.send(odrive.encode("Get_Encoder_Estimates", 0, Pos_Estimate=0.0, Vel_Estimate=math.nan))
            sent["bad_value"] += 1
            rogue.send(can.Message(is_error_frame=True))
            sent["error_frame"] += 1
        assert wait_for(lambda: all(rig.driver.counters.get(k) == n for k, n in sent.items()), 2.0), rig.driver.counters
        assert wait_for(lambda: all(rig.pair.counters.get(k) == sent[k] for k in
                                    ("bad_dlc", "unknown_cmd", "other_node", "extended_id", "error_frame")), 2.0)
    finally:
        rogue.shutdown()
    for kind, n in sent.items():
        assert rig.driver.counters.get(kind) == n, kind
    assert rig.driver.fault is None
    assert rig.driver.read().v == pytest.approx(0.2, abs=1e-3)
    for kind in ("bad_dlc", "unknown_cmd", "other_node", "extended_id", "error_frame"):  # the sim counts them too
        assert rig.pair.counters[kind] == sent[kind], kind
    assert rig.pair.axes[0].state == rig.pair.axes[1].state == odrive.AxisState.CLOSED_LOOP_CONTROL


def test_can_log_writes_an_asc_file_with_both_directions(tmp_path):
    path = tmp_path / "odrive.asc"
    r = Rig(can_log=str(path)).start()
    try:
        r.driver.command(0.1, 0.0)
        assert wait_for(r.reached, 1.0)
    finally:
        r.close()
    logged = list(can.ASCReader(str(path)))
    tx = {m.arbitration_id for m in logged if not m.is_rx}
    rx = {m.arbitration_id for m in logged if m.is_rx}
    assert {0x018, 0x00B, 0x007, 0x00D, 0x02D, 0x027} <= tx  # Clear_Errors, mode, state, Set_Input_Vel
    assert {0x001, 0x009, 0x021, 0x029} <= rx  # heartbeats and encoder estimates of both axes
    vel = [m for m in logged if m.arbitration_id == 0x02D and dbc_decode(m)[1]["Input_Vel"] != 0.0]
    assert dbc_decode(vel[0])[1]["Input_Vel"] == pytest.approx(-0.1 / (2 * math.pi * 0.1) * 2.0, rel=1e-6)


# --- the same driver over slcan on a pseudo-terminal -----------------------------------------
def test_driver_over_slcan_on_a_pty():
    adapter = SlcanPtyBus()
    pair = ODrivePair(adapter, vel_ramp_rate=RAMP).run_realtime()
    cfg = CanConfig(**{**CFG.__dict__, "interface": "slcan", "channel": adapter.slave_path,
                       "bus_options": {"sleep_after_open": 0}})
    d = CanDriver(3, LIMITS, cfg)
    try:
        d.open()
        assert adapter.channel_open and adapter.bitrate == 500_000
        t0 = time.monotonic()
        d.command(0.3, -0.5)
        assert wait_for(lambda: pair.axes[0].input_vel != 0.0, 0.5)
        latency = time.monotonic() - t0
        assert latency < 0.1, latency
        assert wait_for(lambda: d.read() is not None and abs(d.read().v - 0.3) < 1e-4 and abs(d.read().w + 0.5) < 1e-4, 1.0)
        assert d.fault is None and d.counters.get("bad_dlc", 0) == 0
        assert adapter.counters.get("bad_ascii", 0) == 0
        d.close()
        assert wait_for(lambda: not adapter.channel_open, 1.0)  # python-can sent C on shutdown
        assert pair.axes[0].state == pair.axes[1].state == odrive.AxisState.IDLE  # sent before the C
    finally:
        d.close()
        pair.stop()
        adapter.shutdown()


def _read_reply(fd: int, timeout: float = 0.5) -> bytes:
    out = b""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.02)
        if r:
            out += os.read(fd, 1024)
        elif out:
            return out
    return out


def test_pty_adapter_speaks_slcan_and_counts_bad_ascii():
    adapter = SlcanPtyBus()
    fd = os.open(adapter.slave_path, os.O_RDWR | os.O_NOCTTY)
    try:
        def say(line: bytes) -> bytes:
            os.write(fd, line)
            adapter.recv(0.05)  # the adapter handles input while receiving
            return _read_reply(fd, 0.1)

        assert say(b"V\r") == b"V1013\r" and say(b"N\r") == b"NSIM1\r"
        assert say(b"t0010\r") == b"\a"  # closed: no frames
        assert say(b"S6\r") == b"\r" and adapter.bitrate == 500_000
        assert say(b"O\r") == b"\r" and say(b"O\r") == b"\a" and say(b"S4\r") == b"\a"
        for garbage in (b"\xff\xfe\r", b"q12\r", b"t12X8\r", b"t00180011\r", b"t0019" + b"00" * 9 + b"\r", b"x" * 100):
            say(garbage)
        assert adapter.counters["bad_ascii"] == 6 and adapter.counters["closed"] == 1
        os.write(fd, b"t02D80000C03F00000000\r")
        msg = adapter.recv(0.2)
        assert (msg.arbitration_id, bytes(msg.data)) == (0x02D, bytes.fromhex("0000c03f00000000"))
        assert _read_reply(fd, 0.1) == b"z\r"
        adapter.send(odrive.encode("Heartbeat", 1, Axis_State=8))
        assert _read_reply(fd) == b"t0218" + b"0000000008000000" + b"\r"
        adapter.send(odrive.request("Get_Error", 2))
        assert _read_reply(fd) == b"r0438\r"
        assert say(b"C\r") == b"\r"
    finally:
        os.close(fd)
        adapter.shutdown()


def test_sim_axis_defaults_hold_still_until_velocity_mode():
    axis = SimAxis(0, vel_ramp_rate=10.0)
    axis.advance(0.0)
    axis.handle(odrive.decode(odrive.encode("Set_Axis_State", 0, Axis_Requested_State=8)), 0.0)
    axis.handle(odrive.decode(odrive.encode("Set_Input_Vel", 0, Input_Vel=2.0)), 0.0)
    axis.advance(0.2)
    assert axis.vel == 0.0 and axis.errors == 0  # POSITION_CONTROL (the vendor default): no velocity


@pytest.mark.parametrize("node", [63, 64, -1, True, 1.0])
def test_node_ids_are_0_to_62_because_63_is_the_unaddressed_id(node):
    with pytest.raises(ValueError, match=r"node id .* out of range 0\.\.62 \(63 is CANSimple's unaddressed id\)"):
        CanConfig(channel="vcan0", node_left=node, node_right=5)
