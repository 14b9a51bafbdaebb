"""Lock-step with hosted devices: the world's clock drives the device, whatever the wall clock did (issue 16).

Two things made device fleets differ between runs of one seed, both checked here on the real simulated devices:
a device's lock-step time and timers came from how long its wall-clock phase had lasted (sample phases, a 10 Hz
stream that skipped one world step at a step that depended on it), and a command could reach its device after
the world had taken the step's commands (the agent's answer and its command travel on different wires, in no
order). The fleet-level check (the same report twice) is in ``test_hil_fleet.py``.
"""

from __future__ import annotations

import math
import threading
import time

import can
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from stack.comm.lockstep import DeviceWires
from stack.drivers import odrive
from stack.scenario import RobotConfig
from stack.sim_bridge.devices import Body
from stack.sim_bridge.devices_can import OdriveDevice
from stack.sim_bridge.devices_mavlink import RoverDevice

DT = 0.1
POSE = (2.0, -1.0, 0.5)


def odrive_device() -> OdriveDevice:
    robot = RobotConfig(id=2, role="leader", pose=POSE, driver="can", driver_params={"can": {"node_left": 5, "node_right": 6}})
    return OdriveDevice(robot, seed=11, device={"ideal": False})


class Host:
    """A CAN host on the device's slcan pty (python-can's own interface), counting the frames it sent."""

    def __init__(self, dev: OdriveDevice):
        self.bus = can.Bus(interface="slcan", channel=dev.adapter.slave_path, bitrate=500000, sleep_after_open=0)
        self.sent = 0

    def send(self, name: str, node: int, **signals) -> None:
        self.bus.send(odrive.encode(name, node, **signals))
        self.sent += 1

    def close(self) -> None:
        self.bus.shutdown()


def _odrive_run(wall_phase_s: float, steps: int = 15) -> list:
    """The frames the device puts on its wire over ``steps`` lock-step steps (a wheel speed ramp), after a
    wall-clock phase of ``wall_phase_s`` in which the host opened the axes, as a driver does."""
    dev = odrive_device()
    dev.start()
    host = Host(dev)
    wires = DeviceWires(timeout_s=2.0)
    sent: list = []
    try:
        for node in (5, 6):
            host.send("Set_Controller_Mode", node, Control_Mode=odrive.ControlMode.VELOCITY_CONTROL,
                      Input_Mode=odrive.InputMode.VEL_RAMP)
            host.send("Set_Axis_State", node, Axis_Requested_State=odrive.AxisState.CLOSED_LOOP_CONTROL)
        time.sleep(wall_phase_s)
        dev.lockstep(0.0)
        send = dev.pair.send
        dev.pair.send = lambda msgs: (sent.append([(m.arbitration_id, bytes(m.data)) for m in msgs]), send(msgs))
        for k in range(steps):
            t = k * DT
            for node, vel in ((5, 0.3 * k), (6, -0.2 * k)):
                host.send("Set_Input_Vel", node, Input_Vel=vel, Input_Torque_FF=0.0)
            assert wires.deliver({2: dev}, {2: (host.sent, k == 0)}, t, threading.Event()) == []
            _move(dev, k)
        return sent
    finally:
        host.close()
        dev.close()


def _move(dev, k: int) -> None:
    """The rest of world step k: the device's actuators over it, then the body (standing at POSE) reported."""
    v, w = dev.motion((k + 1) * DT)
    dev.report((k + 1) * DT, Body(*POSE, v, w))


def test_an_odrive_in_lock_step_sends_the_same_frames_whatever_its_wall_clock_phase_lasted():
    short, long = _odrive_run(0.03), _odrive_run(0.37)
    assert all(len([f for f in step if odrive.split_id(f[0])[1] == odrive.cmd_id("Get_Encoder_Estimates")]) == 20
               for step in short)  # both axes' 100 Hz estimates, every step
    assert short == long  # the same estimates (positions along the ramp) and heartbeats, at the same steps


def _rover_run(wall_phase_s: float, steps: int = 25) -> list[list[dict]]:
    """What a ground station hears from the rover per 0.1 s lock-step step (its 1 Hz heartbeat, position and
    attitude at 10 Hz), after a wall-clock phase of ``wall_phase_s`` in which it asked for them."""
    robot = RobotConfig(id=1, role="leader", pose=POSE, driver="mavlink")
    dev = RoverDevice(robot, device={"ideal": False})
    dev.start()
    gs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{dev.rover.port}", source_system=255, source_component=190,
                                    dialect="ardupilotmega")
    try:
        for msg_id in (mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_ATTITUDE):
            gs.mav.command_long_send(1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e5, 0, 0, 0, 0, 0)
        time.sleep(wall_phase_s)
        while gs.recv_msg() is not None:  # what it said on the wall clock
            pass
        dev.lockstep(0.0)
        heard = []
        for k in range(steps):
            dev.take_commands(k * DT)
            _move(dev, k)
            time.sleep(0.005)
            heard.append([])
            while (m := gs.recv_msg()) is not None:
                heard[-1].append(m.to_dict())  # the fields (time_boot_ms among them), not the header's sequence
        return heard
    finally:
        gs.close()
        dev.close()


def test_a_rover_in_lock_step_says_the_same_whatever_its_wall_clock_phase_lasted():
    short, long = _rover_run(0.05), _rover_run(0.62)
    assert [len(step) for step in short] == [2] * 9 + [3] + [2] * 9 + [3] + [2] * 5  # the heartbeat each 10th step
    assert short == long


def test_the_world_takes_a_step_s_commands_only_once_the_device_has_all_its_driver_sent():
    dev = odrive_device()
    dev.start()
    host = Host(dev)
    wires = DeviceWires(timeout_s=0.3)
    try:
        for node in (5, 6):
            host.send("Set_Controller_Mode", node, Control_Mode=2, Input_Mode=1)
            host.send("Set_Axis_State", node, Axis_Requested_State=8)
        time.sleep(0.1)
        dev.lockstep(0.0)
        assert wires.deliver({2: dev}, {2: (host.sent, True)}, 0.0, threading.Event()) == []
        # the answer of step 1 is in before its command reaches the device (here: 50 ms later)
        late = threading.Timer(0.05, lambda: host.send("Set_Input_Vel", 5, Input_Vel=1.5, Input_Torque_FF=0.0))
        late.start()
        assert wires.deliver({2: dev}, {2: (host.sent + 1, False)}, DT, threading.Event()) == []
        late.join()
        assert dev.pair.axes[5].input_vel == pytest.approx(1.5)  # taken in step 1, not the next
        # a message the driver counted that never arrives: the step goes on after the bound, said so
        assert wires.deliver({2: dev}, {2: (host.sent + 1, False)}, 2 * DT, threading.Event()) == [2]
        assert wires.late == 1
        # a restarted agent (sync: a new driver whose count starts from 0) is counted from where the device is
        host.send("Set_Input_Vel", 5, Input_Vel=0.0, Input_Torque_FF=0.0)
        time.sleep(0.05)
        assert wires.deliver({2: dev}, {2: (1, True)}, 3 * DT, threading.Event()) == []
        late = threading.Timer(0.05, lambda: host.send("Set_Input_Vel", 5, Input_Vel=-0.5, Input_Torque_FF=0.0))
        late.start()
        assert wires.deliver({2: dev}, {2: (2, False)}, 4 * DT, threading.Event()) == []
        late.join()  # its send returns after the device has the frame (the serial flush): not after the bus is closed
        assert dev.pair.axes[5].input_vel == pytest.approx(-0.5)
        assert math.isclose(dev.device_time(4 * DT), dev.device_time(0.0) + 4 * DT)
    finally:
        host.close()
        dev.close()
