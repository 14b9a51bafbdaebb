"""The simulated ODrive pair as a CAN host sees it, every reply checked against the vendor's DBC.

The host side is raw python-can frames built and decoded with ``cantools`` from the shared
copy of the DBC (``/work/shared/protocols`` when present, else the driver's package copy),
never with our ``stack.drivers.odrive`` module: a reply our codec and the DBC disagreed on
would fail here. The hardware-like device runs behind the simulated slcan adapter, as the
world hosts it, opened with python-can's own ``slcan`` interface.
"""

from __future__ import annotations

import itertools
import math
import time
from pathlib import Path

import can
import cantools
import pytest

from stack.scenario import RobotConfig
from stack.sim_bridge.devices import Body, DeviceError
from stack.sim_bridge.devices_can import OdriveDevice, OdriveDeviceConfig
from stack.sim_bridge.odrive_sim import MotorModel, ODrivePair

SHARED = Path("/work/shared/protocols/odrive-cansimple-0.6.10.dbc")
PACKAGE = Path(__file__).resolve().parents[1] / "stack/drivers/odrive/odrive-cansimple-0.6.10.dbc"
DB = cantools.database.load_file(str(SHARED if SHARED.exists() else PACKAGE))
_ch = itertools.count()
GETS = ("Get_Version", "Get_Error", "Get_Encoder_Estimates", "Get_Iq", "Get_Temperature", "Get_Bus_Voltage_Current",
        "Get_Torques", "Get_Powers")


def msg(name: str, node: int):
    return DB.get_message_by_name(f"Axis{node}_{name}")


def frame(name: str, node: int, **signals) -> can.Message:
    m = msg(name, node)
    data = m.encode({s.name: signals.get(s.name, 0) for s in m.signals}) if m.signals else b""
    return can.Message(arbitration_id=m.frame_id, is_extended_id=False, data=data)


def rtr(name: str, node: int) -> can.Message:
    m = msg(name, node)
    return can.Message(arbitration_id=m.frame_id, is_extended_id=False, is_remote_frame=True, dlc=m.length)


def replies(host: can.BusABC, timeout: float = 0.2) -> list[tuple[str, dict]]:
    out = []
    end = time.monotonic() + timeout
    while (m := host.recv(max(0.0, end - time.monotonic()))) is not None:
        d = DB.get_message_by_frame_id(m.arbitration_id)
        out.append((d.name, d.decode(m.data, decode_choices=False)))
    return out


@pytest.fixture
def pair_and_host():
    ch = f"odrive-hw-{next(_ch)}"
    sim_bus, host = can.Bus(interface="virtual", channel=ch), can.Bus(interface="virtual", channel=ch)
    pair = ODrivePair(sim_bus, node_ids=(3, 4))
    try:
        yield pair, host
    finally:
        sim_bus.shutdown()
        host.shutdown()


def spin_up(pair, host, node: int, vel: float, t_end: float, dt: float = 0.01) -> float:
    """Closed loop, velocity ramp, Set_Input_Vel; step the pair on our clock to ``t_end``."""
    for f in (frame("Set_Controller_Mode", node, Control_Mode=2, Input_Mode=2),
              frame("Set_Axis_State", node, Axis_Requested_State=8)):
        host.send(f)
    t = 0.0
    pair.step(t)
    host.send(frame("Set_Input_Vel", node, Input_Vel=vel))
    while t < t_end - 1e-9:
        t = round(t + dt, 9)
        host.send(frame("Set_Input_Vel", node, Input_Vel=vel))  # the watchdog's food
        pair.step(t)
    replies(host, 0.05)  # the periodic frames so far
    return t


def test_every_get_request_is_answered_as_the_dbc_lays_it_out(pair_and_host):
    pair, host = pair_and_host
    pair.axes[3].vel_ramp_rate = 4.0
    t = spin_up(pair, host, 3, 3.0, 0.5)  # still ramping at 4 rev/s^2: accelerating, 2 rev/s
    for name in GETS:
        host.send(rtr(name, 3))
    pair.step(t)
    got = dict(r for r in replies(host) if not r[0].endswith(("Heartbeat",)))
    assert set(got) >= {f"Axis3_{n}" for n in GETS}, sorted(got)
    v = got["Axis3_Get_Version"]
    assert (v["Fw_Version_Major"], v["Fw_Version_Minor"], v["Fw_Version_Revision"]) == (0, 6, 10)
    enc = got["Axis3_Get_Encoder_Estimates"]
    assert enc["Vel_Estimate"] == pytest.approx(2.0, abs=0.05) and enc["Pos_Estimate"] == pytest.approx(0.5, abs=0.05)
    m = MotorModel()
    torque = got["Axis3_Get_Torques"]["Torque_Estimate"]
    assert torque == pytest.approx(m.inertia * 2 * math.pi * 4.0 + m.viscous * enc["Vel_Estimate"], rel=1e-3)
    assert got["Axis3_Get_Torques"]["Torque_Target"] == pytest.approx(torque)
    iq = got["Axis3_Get_Iq"]["Iq_Measured"]
    assert iq == pytest.approx(torque / m.torque_constant, rel=1e-5) and got["Axis3_Get_Iq"]["Iq_Setpoint"] == pytest.approx(iq)
    p = got["Axis3_Get_Powers"]
    assert p["Mechanical_Power"] == pytest.approx(torque * 2 * math.pi * enc["Vel_Estimate"], rel=1e-3)
    assert p["Electrical_Power"] == pytest.approx(p["Mechanical_Power"] + 1.5 * m.phase_resistance * iq ** 2, rel=1e-4)
    bus = got["Axis3_Get_Bus_Voltage_Current"]
    assert bus["Bus_Voltage"] == 24.0 and bus["Bus_Current"] == pytest.approx(p["Electrical_Power"] / 24.0, rel=1e-4)
    temp = got["Axis3_Get_Temperature"]
    assert m.ambient < temp["FET_Temperature"] < temp["Motor_Temperature"] < 150.0
    assert got["Axis3_Get_Error"] == {"Active_Errors": 0, "Disarm_Reason": 0}
    assert pair.axes[4].state == 1 and not any(n.startswith("Axis4_Get_Iq") for n in got)  # the other axis: idle, silent


def test_idle_axis_reports_no_torque_and_set_absolute_position_moves_the_count(pair_and_host):
    pair, host = pair_and_host
    pair.step(0.0)
    replies(host, 0.05)  # the first periodic frames
    host.send(rtr("Get_Torques", 4))
    host.send(frame("Set_Absolute_Position", 4, Position=12.25))
    host.send(rtr("Get_Encoder_Estimates", 4))
    pair.step(0.001)
    got = [r for r in replies(host) if r[0] in ("Axis4_Get_Torques", "Axis4_Get_Encoder_Estimates")]
    assert got[0] == ("Axis4_Get_Torques", {"Torque_Target": 0.0, "Torque_Estimate": 0.0})
    assert got[-1][1]["Pos_Estimate"] == 12.25
    t = spin_up(pair, host, 4, 1.0, 0.3)
    host.send(rtr("Get_Encoder_Estimates", 4))
    pair.step(t)
    pos = [r[1]["Pos_Estimate"] for r in replies(host) if r[0] == "Axis4_Get_Encoder_Estimates"][-1]
    assert pos > 12.25 + 0.1  # it counts on from where it was set


# --- the hosted device, hardware-like, behind the slcan pty -----------------------------------------------
def device(**settings) -> OdriveDevice:
    robot = RobotConfig(id=2, role="leader", pose=(2.0, -1.0, 0.5), driver="can",
                        driver_params={"can": {"node_left": 5, "node_right": 6}})
    return OdriveDevice(robot, seed=11, device=settings)


def test_encoders_count_from_power_up_and_every_estimate_goes_out_at_its_own_time():
    dev = device(ideal=False)
    dev.start()
    host = can.Bus(interface="slcan", channel=dev.adapter.slave_path, bitrate=500000, sleep_after_open=0)
    try:
        start = {n: dev.pair.axes[n].pos for n in (5, 6)}
        assert all(0.0 <= p < 1.0 for p in start.values()) and start[5] != start[6]  # shaft angles, not 0
        again = device(ideal=False)
        again.start()
        assert {n: again.pair.axes[n].pos for n in (5, 6)} == start  # seeded: a rerun powers up the same
        again.close()
        dev.lockstep(0.0)
        for node in (5, 6):
            for f in (frame("Set_Controller_Mode", node, Control_Mode=2, Input_Mode=1),
                      frame("Set_Axis_State", node, Axis_Requested_State=8)):
                host.send(f)
        time.sleep(0.05)
        t = 0.0
        for node, vel in ((5, 2.0), (6, -2.0)):
            host.send(frame("Set_Input_Vel", node, Input_Vel=vel))
        time.sleep(0.05)
        replies(host, 0.1)
        dev.take_commands(t)
        v, w = dev.motion(t + 0.1)
        dev.report(t + 0.1, Body(2.0, -1.0, 0.5, v, w))
        got = replies(host, 0.3)
        enc = {n: [s for name, s in got if name == f"Axis{n}_Get_Encoder_Estimates"] for n in (5, 6)}
        assert len(enc[5]) == len(enc[6]) == 10  # 100 Hz over the 0.1 s step, not one
        pos5 = [s["Pos_Estimate"] for s in enc[5]]
        assert [b - a for a, b in zip(pos5, pos5[1:])] == pytest.approx([0.02] * 9, abs=1e-5)  # 2 rev/s x 10 ms
        assert 0.0 < pos5[0] - start[5] <= 0.02 + 1e-5  # the first estimate within 10 ms of the command (its own phase)
        pos6 = [s["Pos_Estimate"] for s in enc[6]]
        assert pos6[-1] - pos6[0] == pytest.approx(-0.18, abs=1e-5) and 0.0 < start[6] - pos6[0] <= 0.02 + 1e-5
        assert v == pytest.approx(2.0 * 2 * math.pi * 0.098)  # both wheels forward (the right motor is mirrored)
    finally:
        host.shutdown()
        dev.close()


def test_ideal_device_counts_from_zero_and_sends_the_newest_estimate():
    assert not OdriveDeviceConfig().ideal  # hardware-like is the default
    dev = device(ideal=True)
    dev.start()
    try:
        assert dev.device_config.ideal and all(dev.pair.axes[n].pos == 0.0 for n in (5, 6))
        assert not dev.pair.axes[5].all_samples
    finally:
        dev.close()


@pytest.mark.parametrize("settings, field", [
    ({"power_up_pos_rev": [0.1]}, "power_up_pos_rev"), ({"power_up_pos_rev": [0.1, math.nan]}, "power_up_pos_rev right"),
    ({"all_encoder_samples": "yes"}, "all_encoder_samples"), ({"encoders": 1}, "encoders"),
])
def test_bad_settings_name_the_field(settings, field):
    with pytest.raises(DeviceError, match=f"robot 2: can device: .*{field}"):
        device(**settings)


def test_our_can_driver_copes_with_the_hardware_like_pair():
    """Our driver on the hardware-like device: opens, commands, and gets one odometry per pair of estimates."""
    from stack.drivers.base import DriverLimits
    from stack.drivers.can import CanDriver

    dev = device(ideal=False)
    dev.start()
    sim_t = [0.0]
    odoms: list = []
    drv = CanDriver(2, DriverLimits(v_max=2.0, w_max=4.0), clock=lambda: sim_t[0], on_odom=odoms.append,
                    **dev.driver_params(), node_left=5, node_right=6)
    try:
        drv.open()  # against the device on the wall clock
        dev.lockstep(0.0)
        drv.command(0.5, 0.0)
        time.sleep(0.05)
        for k in range(5):
            t = 0.1 * k
            dev.take_commands(t)
            v, w = dev.motion(t + 0.1)
            dev.report(t + 0.1, Body(2.0, -1.0, 0.5, v, w))
            sim_t[0] = t + 0.1
            time.sleep(0.05)
        n = len(odoms)
        dev.take_commands(0.5)
        dev.report(0.6, Body(2.0, -1.0, 0.5, *dev.motion(0.6)))
        deadline = time.monotonic() + 1.0
        while len(odoms) < n + 10 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(odoms) == n + 10  # ten estimate pairs in the step: ten odometry samples
        assert odoms[-1].v == pytest.approx(0.5, abs=1e-4) and drv.fault is None
    finally:
        drv.close()
        dev.close()
