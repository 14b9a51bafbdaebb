"""The MAVLink driver (ArduPilot Rover, GUIDED) and the simulated rover, over UDP loopback.

The simulated rover is checked on its own in lock-step time with a raw MAVLink client (hand
values in NED, the target timeout, the GCS failsafe); the driver runs against it in wall
time, or, where a test counts keepalives or times the heartbeat timeout, on fake clocks. What the driver put on the wire is decoded again with a fresh pymavlink parser.
"""

from __future__ import annotations

import math
import random
import socket
import statistics
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from conftest import wait_for
from stack.drivers import DriverError, DriverLimits
from stack.drivers.mavlink import (MODE_GUIDED, MODE_HOLD, TYPE_MASK_VEL_YAW_RATE, MavlinkConfig, MavlinkDriver,
                                   forward_speed, mode_name, ned_to_world, result_name, world_to_ned)
from stack.drivers.testing import FakeClock, settle
from stack.sim_bridge.rover_sim import SimRover

LIMITS = DriverLimits(v_max=1.0, w_max=2.0, cmd_timeout=5.0)
RATE = 20.0  # [Hz] telemetry asked for in the tests


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def same_angle(a: float, b: float, tol: float = 1e-6) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) < tol


class Rig:
    """A simulated rover on wall time sending to a driver that listens (``udpin``) on a free loopback port."""

    def __init__(self, heartbeat_period: float = 0.25, clock=time.monotonic, wall=time.monotonic, **cfg):
        self.port = free_udp_port()
        self.sim = SimRover(peer=("127.0.0.1", self.port), heartbeat_period=heartbeat_period, accel_max=4.0,
                            yaw_accel_max=8.0)
        self.malformed: list[str] = []
        self.cfg = MavlinkConfig(**{"connection": f"udpin:127.0.0.1:{self.port}", "position_rate": RATE,
                                    "attitude_rate": RATE, "ack_timeout": 0.3, "connect_timeout": 2.0,
                                    "mode_timeout": 2.0, "arm_timeout": 2.0, **cfg})
        self.driver = MavlinkDriver(4, LIMITS, self.cfg, clock=clock, wall=wall, on_malformed=self.malformed.append)

    def start(self) -> "Rig":
        self.sim.run_realtime()
        self.driver.open()
        return self

    def close(self) -> None:
        self.driver.close()
        self.sim.kill()


@pytest.fixture
def rig():
    r = Rig().start()
    yield r
    r.close()


class Client:
    """A raw MAVLink GCS (255/190) on its own loopback socket, for the simulated rover in lock-step."""

    def __init__(self, sim: SimRover, system: int = 255, component: int = 190):
        self.sim = sim
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.enc = mav.MAVLink(self, srcSystem=system, srcComponent=component)

    def write(self, buf: bytes) -> None:
        self.sock.sendto(buf, self.sim.address)

    def send(self, msg) -> None:
        self.enc.send(msg)

    def heartbeat(self) -> None:
        self.send(self.enc.heartbeat_encode(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0))

    def command(self, command: int, *params: float) -> None:
        self.send(self.enc.command_long_encode(1, 1, command, 0, *(list(params) + [0.0] * 7)[:7]))

    def target(self, vx: float, yaw_rate: float) -> None:
        self.send(self.enc.set_position_target_local_ned_encode(0, 1, 1, mav.MAV_FRAME_BODY_NED, TYPE_MASK_VEL_YAW_RATE,
                                                                0, 0, 0, vx, 0, 0, 0, 0, 0, 0, yaw_rate))

    def received(self) -> list:
        out, parser = [], mav.MAVLink(None)
        while True:
            try:
                data = self.sock.recv(65535)
            except BlockingIOError:
                return out
            out += parser.parse_buffer(data) or []

    def close(self) -> None:
        self.sock.close()


def guided_and_armed(sim: SimRover, c: Client, t: float) -> None:
    c.heartbeat()
    c.send(c.enc.set_mode_encode(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MODE_GUIDED))  # the SET_MODE message path
    c.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    sim.step(t)
    assert sim.mode == MODE_GUIDED and sim.armed


# --- conversions and constants ------------------------------------------------------------
def test_frames_and_constants_by_hand():
    assert TYPE_MASK_VEL_YAW_RATE == 1511 and MODE_GUIDED == 15 and MODE_HOLD == 4
    assert mode_name(0) == "MANUAL" and mode_name(4) == "HOLD" and mode_name(99) == "mode 99"
    assert result_name(mav.MAV_RESULT_DENIED) == "MAV_RESULT_DENIED"
    # (north, east, yaw_ned) -> (x east, y north, yaw ccw from east)
    x, y, yaw = ned_to_world(3.0, 4.0, 0.0)  # facing north
    assert (x, y) == (4.0, 3.0) and same_angle(yaw, math.pi / 2)
    assert same_angle(ned_to_world(0, 0, math.pi / 2)[2], 0.0)  # east
    assert same_angle(ned_to_world(0, 0, math.pi)[2], -math.pi / 2)  # south
    assert same_angle(ned_to_world(0, 0, -math.pi / 2)[2], math.pi)  # west
    assert same_angle(ned_to_world(0, 0, math.radians(30))[2], math.radians(60))
    n, e, yn = world_to_ned(2.0, -1.0, math.pi / 6)
    assert (n, e) == (-1.0, 2.0) and same_angle(yn, math.pi / 3)
    assert forward_speed(1.0, 0.0, math.pi / 2) == pytest.approx(0.0, abs=1e-12)  # moving north, facing east
    assert forward_speed(-1.0, 0.0, math.pi) == pytest.approx(1.0)  # moving south, facing south


def test_config_rejects_bad_settings():
    with pytest.raises(ValueError, match="unknown settings bogus"):
        MavlinkDriver(1, LIMITS, bogus=1)
    with pytest.raises(ValueError, match="not a link"):
        MavlinkConfig(connection="flight.tlog")
    with pytest.raises(ValueError, match="keepalive_period"):
        MavlinkConfig(keepalive_period=2.0)
    d = MavlinkDriver(1, LIMITS, MavlinkConfig(), heartbeat_timeout=2.0)
    assert d.config.heartbeat_timeout == 2.0


# --- the simulated rover in lock-step -----------------------------------------------------
def test_sim_telemetry_in_ned_by_hand():
    with SimRover(integrate_pose=False) as sim:  # the world owns the pose
        c = Client(sim)
        c.heartbeat()
        for msg_id in (32, 30):
            c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 100_000)
        c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, 147, 100_000)  # BATTERY_STATUS: not streamed
        c.command(31000)  # a command the rover lacks
        sim.set_pose(2.0, -1.0, math.pi / 6, v=0.5, w=0.2)  # world: x east 2, y north -1, 30 deg ccw from east
        sim.step(0.0)
        got = c.received()
        acks = [(m.command, m.result) for m in got if m.get_type() == "COMMAND_ACK"]
        assert acks == [(511, mav.MAV_RESULT_ACCEPTED), (511, mav.MAV_RESULT_ACCEPTED),
                        (511, mav.MAV_RESULT_FAILED), (31000, mav.MAV_RESULT_UNSUPPORTED)]
        hb = next(m for m in got if m.get_type() == "HEARTBEAT")
        assert (hb.type, hb.autopilot, hb.custom_mode) == (mav.MAV_TYPE_GROUND_ROVER, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 4)
        assert hb.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        pos = next(m for m in got if m.get_type() == "LOCAL_POSITION_NED")
        att = next(m for m in got if m.get_type() == "ATTITUDE")
        assert (pos.x, pos.y) == pytest.approx((-1.0, 2.0))  # north = world y, east = world x
        assert att.yaw == pytest.approx(math.pi / 3)  # 60 deg clockwise from north
        assert (pos.vx, pos.vy) == pytest.approx((0.25, 0.5 * math.cos(math.pi / 6)), abs=1e-6)
        assert att.yawspeed == pytest.approx(-0.2)  # counter-clockwise in the world is negative in NED
        sim.step(0.05)
        assert not [m for m in c.received() if m.get_type() == "ATTITUDE"]  # 10 Hz: not due at 0.05 s
        sim.step(0.1)
        att = [m for m in c.received() if m.get_type() == "ATTITUDE"]
        assert att and att[-1].yaw == pytest.approx(math.pi / 3) and att[-1].yawspeed == pytest.approx(-0.2)
        assert sim.pose == pytest.approx((2.0, -1.0, math.pi / 6))  # stepping did not move the world's pose
        c.close()


def test_sim_target_rules_and_3s_timeout():
    with SimRover(accel_max=1.0) as sim:
        c = Client(sim)
        c.heartbeat()
        c.target(0.5, 0.0)  # HOLD, disarmed: refused
        c.command(mav.MAV_CMD_DO_SET_MODE, 1, 99)  # no such mode
        sim.step(0.0)
        assert sim.counters["target_refused"] == 1 and sim.target == (0.0, 0.0)
        assert [(m.command, m.result) for m in c.received() if m.get_type() == "COMMAND_ACK"] == \
            [(176, mav.MAV_RESULT_FAILED)]
        guided_and_armed(sim, c, 0.0)
        c.target(0.5, -0.4)  # NED yaw rate -0.4: counter-clockwise 0.4 rad/s in our frame
        t = 0.0
        sim.step(t)
        assert sim.target == pytest.approx((0.5, 0.4))
        while t < 2.9:
            t = round(t + 0.05, 3)
            c.heartbeat()
            sim.step(t)
        assert sim.body_velocity() == pytest.approx((0.5, 0.4))
        assert sim.pose[2] > 0.9  # world yaw grew (counter-clockwise)
        while t < 3.8:
            t = round(t + 0.05, 3)
            c.heartbeat()
            sim.step(t)
        assert sim.counters["target_timeout"] == 1 and sim.body_velocity() == (0.0, 0.0)
        assert sim.mode == MODE_GUIDED and sim.armed  # it stops, it does not leave GUIDED
        c.close()


def test_sim_gcs_failsafe_holds():
    with SimRover(fs_gcs_timeout=5.0) as sim:
        c = Client(sim)
        guided_and_armed(sim, c, 0.0)
        sim.step(4.9)
        assert sim.mode == MODE_GUIDED and sim.failsafe is None
        sim.step(5.1)
        assert sim.mode == MODE_HOLD and sim.failsafe == "GCS" and sim.counters["fs_gcs"] == 1
        c.heartbeat()
        sim.step(5.2)
        assert sim.failsafe is None and sim.mode == MODE_HOLD  # the GCS is back; the mode stays
        c.close()


# --- the driver against the simulated rover ------------------------------------------------
def test_open_sets_guided_arms_and_asks_for_telemetry(rig):
    sim, d = rig.sim, rig.driver
    assert sim.mode == MODE_GUIDED and sim.armed
    assert sim.intervals == pytest.approx({32: 1 / RATE, 30: 1 / RATE})
    assert d.vehicle_mode == "GUIDED" and d.vehicle_armed and d.fault is None
    assert wait_for(lambda: d.read() is not None and d.position_fix() is not None, 1.0)
    assert sim.counters["gcs_heartbeat"] >= 1 and rig.malformed == []


def test_command_signs_odometry_and_position_fix(rig):
    sim, d = rig.sim, rig.driver
    sim.set_pose(2.0, -1.0, math.pi / 6)  # world: still, at (2, -1) facing 30 deg ccw from east
    fix = wait_for(lambda: (f := d.position_fix()) and f[0] == pytest.approx(2.0, abs=1e-4) and f, 1.0)
    assert fix, d.position_fix()
    assert fix[1] == pytest.approx(-1.0, abs=1e-4) and fix[2] == d.config.position_std
    assert wait_for(lambda: (o := d.read()) and same_angle(o.pose[2], math.pi / 6, 1e-5), 1.0), d.read()
    yaw_ned0 = world_to_ned(*sim.pose)[2]
    d.command(0.5, 0.4)
    assert wait_for(lambda: sim.body_velocity() == pytest.approx((0.5, 0.4), abs=1e-6), 1.0), sim.body_velocity()
    assert wait_for(lambda: (o := d.read()) and o.v == pytest.approx(0.5, abs=0.01)
                    and o.w == pytest.approx(0.4, abs=0.01), 1.0), d.read()
    # w > 0: NED yaw decreases
    assert wait_for(lambda: math.remainder(world_to_ned(*sim.pose)[2] - yaw_ned0, 2 * math.pi) < -0.1, 1.0)
    x, y, _, _ = d.position_fix()
    yaw = d.read().pose[2]
    sx, sy, syaw = sim.pose
    assert (x, y) == pytest.approx((sx, sy), abs=0.1) and same_angle(yaw, syaw, 0.1)
    d.command(-0.3, -0.5)  # reverse, turning clockwise
    assert wait_for(lambda: (o := d.read()) and o.v == pytest.approx(-0.3, abs=0.01)
                    and o.w == pytest.approx(-0.5, abs=0.01), 1.5), d.read()
    assert sim.target == pytest.approx((-0.3, -0.5))


def test_keepalive_feeds_the_target():
    clock, wall = FakeClock(), FakeClock()
    rig = Rig(clock=clock, wall=wall).start()
    try:
        rig.driver.command(0.2, 0.0)
        assert wait_for(lambda: rig.sim.target == pytest.approx((0.2, 0.0)), 0.5)  # the command itself is there
        n0, hb0 = rig.sim.counters["target"], rig.sim.counters["gcs_heartbeat"]
        clock.run(rig.driver, 1.0, 0.125, wall)  # no new command: resent every 0.25 s; our heartbeat at 1 Hz
        assert wait_for(lambda: rig.sim.counters["target"] - n0 == 4, 1.0), rig.sim.counters["target"] - n0
        assert wait_for(lambda: rig.sim.counters["gcs_heartbeat"] - hb0 == 1, 1.0)
        assert wait_for(lambda: rig.sim.body_velocity()[0] == pytest.approx(0.2), 1.0)  # the rover kept going
        assert rig.sim.counters["target"] - n0 == 4
    finally:
        rig.close()


def test_arming_refused_is_one_clear_line():
    r = Rig()
    r.sim.arming_check_failed = True
    r.sim.run_realtime()
    try:
        with pytest.raises(DriverError) as e:
            r.driver.open()
        text = str(e.value)
        assert "arming refused: MAV_RESULT_DENIED" in text and "\n" not in text
        assert wait_for(lambda: r.sim.mode == MODE_HOLD, 0.5) and not r.sim.armed  # given back in HOLD
        with pytest.raises(DriverError, match="closed driver"):
            r.driver.command(0.1, 0.0)
    finally:
        r.sim.kill()


def test_no_vehicle_is_a_clear_error():
    d = MavlinkDriver(1, LIMITS, MavlinkConfig(connection=f"udpin:127.0.0.1:{free_udp_port()}", connect_timeout=0.3))
    t0 = time.monotonic()
    with pytest.raises(DriverError, match="no HEARTBEAT from system 1"):
        d.open()
    assert time.monotonic() - t0 < 1.0


def test_mode_yanked_to_hold_faults_naming_it():
    r = Rig(heartbeat_period=1.0).start()  # ArduPilot's 1 Hz heartbeat
    try:
        r.driver.command(0.3, 0.0)
        t0 = time.monotonic()
        r.sim.force_mode("HOLD")
        assert wait_for(lambda: r.driver.fault, 1.5), "no fault 1.5 s after the mode change"
        assert "HOLD" in r.driver.fault and "\n" not in r.driver.fault
        assert time.monotonic() - t0 < 1.5
        assert r.driver.command(0.5, 0.5) == (0.0, 0.0)
        r.driver.close()
        assert r.sim.mode == MODE_HOLD and r.sim.armed  # someone else's now: close leaves mode and arming alone
    finally:
        r.close()


def test_disarmed_under_the_driver_faults(rig):
    rig.sim.disarm()
    assert wait_for(lambda: rig.driver.fault, 1.0)
    assert "disarmed" in rig.driver.fault


def test_vehicle_heartbeat_loss_faults_after_heartbeat_timeout():
    """The timeout on the driver's clock (fake: it stands still while the last heartbeats arrive); our
    heartbeat and the keepalive follow the wall, so the vehicle's failsafe stays fed meanwhile."""
    clock = FakeClock()
    r = Rig(heartbeat_period=1.0, clock=clock).start()
    try:
        r.driver.command(0.4, 0.0)
        assert wait_for(lambda: r.sim.target == pytest.approx((0.4, 0.0)), 0.5)
        r.sim.stop_heartbeats()
        assert settle(lambda: r.driver.counters["heartbeat"], quiet=0.2)
        clock.advance(3.0)  # heartbeat_timeout
        r.driver.supervise_once()
        assert r.driver.fault is None
        clock.advance(0.125)
        r.driver.supervise_once()
        assert r.driver.fault == "no HEARTBEAT from system 1 for 3.1 s"
        assert wait_for(lambda: r.sim.target == (0.0, 0.0), 0.5)  # the trip sent a zero target
        assert r.driver.liveness()["heartbeat"] == 3.125
        t1 = time.monotonic()
        r.driver.close()  # the vehicle does not answer: no waiting for ACKs
        assert time.monotonic() - t1 < 0.5
        assert wait_for(lambda: r.sim.mode == MODE_HOLD and not r.sim.armed, 0.5)
    finally:
        r.close()


def test_malformed_and_foreign_traffic_counted_and_ignored(rig):
    d, sim = rig.driver, rig.sim
    assert wait_for(lambda: d.read() is not None, 1.0)
    vehicle = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    stranger = mav.MAVLink(None, srcSystem=42, srcComponent=1)
    hold_disarmed = lambda enc: enc.heartbeat_encode(10, 3, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MODE_HOLD, 3).pack(enc)
    bad_crc = bytearray(hold_disarmed(vehicle))
    bad_crc[-1] ^= 0xFF
    unknown = bytes([0xFD, 4, 0, 0, 7, 1, 1, 0x21, 0x43, 0x65, 1, 2, 3, 4, 0xAA, 0xBB])  # msg id 0x654321
    whole = hold_disarmed(vehicle)
    rng = random.Random(7)
    garbage = bytes(rng.choice([b for b in range(256) if b not in (0xFD, 0xFE)]) for _ in range(40))
    datagrams = [garbage, bytes(bad_crc), unknown, whole[: len(whole) // 2], hold_disarmed(stranger),
                 stranger.attitude_encode(0, 0, 0, 2.0, 0, 0, 5.0).pack(stranger), garbage + whole[:5]]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        for _ in range(3):
            for dg in datagrams:
                s.sendto(dg, ("127.0.0.1", rig.port))
        assert wait_for(lambda: d.counters.get("other_system", 0) >= 6 and d.counters.get("truncated", 0) >= 3, 2.0)
    c = d.counters
    assert c.get("bad_data", 0) >= 3 and c.get("bad_crc", 0) >= 3 and c.get("unknown_msg", 0) >= 3
    assert c.get("truncated", 0) >= 3 and c.get("other_system", 0) >= 6
    assert d.fault is None and d.vehicle_mode == "GUIDED" and d.vehicle_armed
    assert {"mavlink/bad_data", "mavlink/bad_crc", "mavlink/unknown_msg", "mavlink/truncated",
            "mavlink/other_system"} <= set(rig.malformed)
    assert abs(d.read().w) < 1e-6  # the stranger's ATTITUDE (yawspeed 5) never reached the odometry
    d.command(0.3, 0.0)  # and the link still works
    assert wait_for(lambda: sim.body_velocity()[0] == pytest.approx(0.3), 1.0)


def test_close_leaves_the_rover_in_hold_disarmed_and_still(rig):
    sim, d = rig.sim, rig.driver
    d.command(0.6, 0.3)
    assert wait_for(lambda: sim.body_velocity()[0] == pytest.approx(0.6), 1.0)
    t0 = time.monotonic()
    d.close()
    assert time.monotonic() - t0 < 2.5  # bounded (two ACKs, the threads' joins), with room for a loaded machine
    assert sim.mode == MODE_HOLD and not sim.armed and sim.target == (0.0, 0.0)
    assert wait_for(lambda: sim.body_velocity() == (0.0, 0.0), 1.0)


def test_everything_sent_decodes_to_the_intended_fields(rig):
    d, sim = rig.driver, rig.sim
    commanded = [(0.4, 0.7), (-0.2, -0.3), (0.0, 0.0)]
    for v, w in commanded[:2]:
        d.command(v, w)
        time.sleep(0.3)
    time.sleep(0.8)
    d.close()
    time.sleep(0.05)
    parser = mav.MAVLink(None)  # strict: any bad byte raises
    sent = [m for _, m in sim.rx_log]
    assert sent
    kinds, commands = set(), []
    for m in sent:
        buf = bytes(m.get_msgbuf())
        assert buf[0] == 0xFD  # MAVLink 2
        again = parser.parse_buffer(buf)
        assert again and len(again) == 1 and again[0].get_type() == m.get_type()
        m = again[0]
        assert (m.get_srcSystem(), m.get_srcComponent()) == (255, 190)
        kinds.add(m.get_type())
        if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
            assert (m.type_mask, m.coordinate_frame, m.target_system, m.target_component) == (1511, 8, 1, 1)
            assert (m.vy, m.vz) == (0.0, 0.0)
            assert any(m.vx == pytest.approx(v) and m.yaw_rate == pytest.approx(-w) for v, w in commanded), m
        elif m.get_type() == "COMMAND_LONG":
            assert (m.target_system, m.target_component) == (1, 1)
            commands.append((m.command, m.param1, m.param2))
        elif m.get_type() == "HEARTBEAT":
            assert (m.type, m.autopilot) == (mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID)
    assert kinds == {"HEARTBEAT", "COMMAND_LONG", "SET_POSITION_TARGET_LOCAL_NED"}
    assert commands == [(176, 1, 15), (511, 32, pytest.approx(1e6 / RATE)), (511, 30, pytest.approx(1e6 / RATE)),
                        (400, 1, 0), (176, 1, 4), (400, 0, 0)]
    yaw_rates = [m.yaw_rate for m in sent if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    assert pytest.approx(-0.7) in yaw_rates and pytest.approx(0.3) in yaw_rates  # w ccw -> NED yaw rate negated


def test_command_to_motion_latency(rig, capsys):
    """driver.command() -> the simulated rover's body velocity starts changing, over UDP loopback."""
    d, sim = rig.driver, rig.sim
    lat = []
    for i in range(30):
        target = 0.3 if i % 2 == 0 else -0.3
        before = sim.body_velocity()[1]
        t0 = time.perf_counter()
        d.command(0.0, target)
        moved = wait_for(lambda: (sim.body_velocity()[1] - before) * target > 0, 0.5, step=0.0002)
        assert moved
        lat.append(time.perf_counter() - t0)
        time.sleep(0.02)
    lat.sort()
    med, p95 = statistics.median(lat) * 1e3, lat[int(0.95 * len(lat)) - 1] * 1e3
    with capsys.disabled():
        print(f"\ncommand-to-motion latency over UDP loopback: median {med:.2f} ms, p95 {p95:.2f} ms, "
              f"max {lat[-1] * 1e3:.2f} ms (n={len(lat)})")
    assert med < 20.0
