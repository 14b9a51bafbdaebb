"""The ``jackal`` driver (ROS 2 Jackal behind zenoh-bridge-ros2dds) and its simulated device.

The CDR payloads are checked against ``rosbags`` deserialisation (and one hand-packed
Twist); driver and device then talk over real Zenoh sessions through a loopback router
(scouting off), each test under its own namespace. The device's controller is stepped in
lock-step sim time; the driver's supervision runs on the wall clock, or, where a test counts
keepalives or times the odometry timeout, on fake clocks stepped by the test.
"""

from __future__ import annotations

import itertools
import math
import struct
import time

import numpy as np
import pytest

from conftest import wait_for
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session
from stack.drivers.base import DriverError, DriverLimits
from stack.drivers.jackal import JackalConfig, JackalDriver
from stack.drivers.testing import FakeClock, settle
from stack.drivers.ros2cdr import (CDR_LE_HEADER, LASER_SCAN, ODOMETRY, TWIST, TYPESTORE, CdrError, decode_laserscan,
                                   decode_odometry, decode_twist, encode_laserscan, encode_odometry, encode_twist,
                                   ros_time, serialize)
from stack.scenario import RobotConfig
from stack.sim_bridge.devices import Body, DeviceError
from stack.sim_bridge.jackal_sim import JackalDevice

T = TYPESTORE.types
WIDE = DriverLimits(v_max=10.0, w_max=10.0, cmd_timeout=5.0)  # wider than a Jackal: its own limits must bite
_ns = itertools.count()


def header(stamp: float, frame: str):
    return T["std_msgs/msg/Header"](stamp=ros_time(stamp), frame_id=frame)


# --- CDR against rosbags --------------------------------------------------------------------
def test_twist_is_the_cdr_a_ros2_node_sends():
    data = encode_twist(0.7, -1.2)
    assert data[:4] == CDR_LE_HEADER == b"\x00\x01\x00\x00"
    assert data == CDR_LE_HEADER + struct.pack("<6d", 0.7, 0.0, 0.0, 0.0, 0.0, -1.2)  # hand-packed, not rosbags
    m = TYPESTORE.deserialize_cdr(data, TWIST)
    assert (m.linear.x, m.linear.y, m.linear.z, m.angular.x, m.angular.y, m.angular.z) == (0.7, 0, 0, 0, 0, -1.2)
    theirs = T[TWIST](linear=T["geometry_msgs/msg/Vector3"](x=-0.25, y=0.0, z=0.0),
                      angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=3.5))
    assert decode_twist(serialize(theirs, TWIST)) == (-0.25, 3.5)


def test_odometry_round_trips_against_rosbags():
    data = encode_odometry(12.25, 3.0, -4.5, 2.9, 0.8, -0.6)
    assert data[:4] == CDR_LE_HEADER
    m = TYPESTORE.deserialize_cdr(data, ODOMETRY)
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (12, 250_000_000)
    assert (m.header.frame_id, m.child_frame_id) == ("odom", "base_link")
    p, q = m.pose.pose.position, m.pose.pose.orientation
    assert (p.x, p.y, p.z) == (3.0, -4.5, 0.0)
    assert (q.x, q.y) == (0.0, 0.0) and q.z == pytest.approx(math.sin(1.45)) and q.w == pytest.approx(math.cos(1.45))
    assert (m.twist.twist.linear.x, m.twist.twist.angular.z) == (0.8, -0.6)
    odo = decode_odometry(data)
    assert (odo.v, odo.w, odo.stamp, odo.step) == (0.8, -0.6, 12.25, -1)
    assert odo.pose == pytest.approx((3.0, -4.5, 2.9))
    # an EKF's message with roll and pitch and an unnormalised quaternion: yaw is still the heading
    yaw, roll = -2.0, 0.1
    cy, sy, cr, sr = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(roll / 2), math.sin(roll / 2)
    quat = T["geometry_msgs/msg/Quaternion"](x=2 * sr * cy, y=2 * sr * sy, z=2 * cr * sy, w=2 * cr * cy)
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.1), orientation=quat)
    twist = T[TWIST](linear=T["geometry_msgs/msg/Vector3"](x=0.3, y=0.01, z=0.0),
                     angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.2))
    theirs = T[ODOMETRY](header=header(1700000000.5, "odom"), child_frame_id="base_link",
                         pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.eye(6).ravel()),
                         twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))
    odo = decode_odometry(serialize(theirs, ODOMETRY))
    assert (odo.v, odo.w, odo.stamp) == (0.3, 0.2, 1700000000.5)
    assert odo.pose == pytest.approx((1.0, 2.0, yaw))


def test_laserscan_round_trips_against_rosbags():
    ranges = [0.5, 1.25, 4.0, 5.0, 2.2]
    data = encode_laserscan(3.5, -math.pi / 2, math.pi / 4, 5.0, ranges)
    assert data[:4] == CDR_LE_HEADER
    m = TYPESTORE.deserialize_cdr(data, LASER_SCAN)
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (3, 500_000_000)
    assert m.angle_min == pytest.approx(-math.pi / 2, abs=1e-6) and m.angle_max == pytest.approx(math.pi / 2, abs=1e-6)
    assert m.angle_increment == pytest.approx(math.pi / 4, abs=1e-6) and m.range_max == 5.0
    assert m.ranges.dtype == np.float32 and m.ranges.tolist() == pytest.approx(ranges, abs=1e-6)
    scan = decode_laserscan(data)
    assert (scan.stamp, scan.range_max) == (3.5, 5.0) and scan.ranges == pytest.approx(tuple(ranges), abs=1e-6)
    assert len(scan.ranges) == 5 and isinstance(scan.ranges, tuple)
    # a real lidar's REP 117 readings: +inf no return, -inf too close, NaN invalid
    theirs = T[LASER_SCAN](header=header(1.0, "laser"), angle_min=-1.0, angle_max=1.0, angle_increment=0.5,
                           time_increment=0.0, scan_time=0.1, range_min=0.05, range_max=10.0,
                           ranges=np.array([1.0, np.inf, -np.inf, np.nan, 11.0], dtype=np.float32),
                           intensities=np.ones(5, dtype=np.float32))
    scan = decode_laserscan(serialize(theirs, LASER_SCAN))
    assert scan.ranges == pytest.approx((1.0, 10.0, 0.05, 10.0, 10.0))


@pytest.mark.parametrize("payload, kind", [
    (b"", "not_cdr"), (b"{\"v\": 1}", "not_cdr"), (b"\x00\x01\x00\x00\x01\x02", "undecodable"),
    (encode_twist(1.0, 0.0), "undecodable"),  # a Twist where an Odometry belongs
    (encode_laserscan(1.0, 0.0, 0.1, 5.0, [1.0] * 3), "undecodable"),
    (encode_odometry(1.0, 0.0, 0.0, 0.0, math.nan, 0.0), "bad_value"),
    (encode_odometry(1.0, math.inf, 0.0, 0.0, 0.0, 0.0), "bad_value"),
])
def test_decoders_name_what_is_wrong(payload, kind):
    with pytest.raises(CdrError) as e:
        decode_odometry(payload)
    assert e.value.kind == kind


def test_config_is_checked_and_settings_override_it():
    assert JackalConfig().key(3, "cmd_vel") == "robot3/cmd_vel"
    assert JackalConfig(namespace="j100_0421").key(3, JackalConfig().odom_topic) == "j100_0421/platform/odom/filtered"
    for bad in ("/robot1", "robot1/", "a//b", "robot*", "ro bot", "", "a/$b"):
        with pytest.raises(ValueError, match="namespace"):
            JackalConfig(namespace=bad)
    with pytest.raises(ValueError, match="keepalive_period"):
        JackalConfig(keepalive_period=0.5)
    with pytest.raises(ValueError, match="odom_timeout"):
        JackalConfig(odom_timeout=math.nan)
    with pytest.raises(ValueError, match="unknown settings bogus"):
        JackalDriver(1, WIDE, session=object(), bogus=1)
    d = JackalDriver(1, WIDE, JackalConfig(namespace="a"), session=object(), namespace="b/c", odom_timeout=0.2)
    assert (d.config.odom_timeout, d.cmd_key, d.scan_key) == (0.2, "b/c/cmd_vel", "b/c/sensors/lidar2d_0/scan")


# --- over Zenoh ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sessions():
    ep = free_tcp_endpoint()
    with open_session(SessionConfig(mode="router", listen=[ep])), \
            open_session(SessionConfig(connect=[ep])) as s_agent, \
            open_session(SessionConfig(connect=[ep])) as s_world:
        yield s_agent, s_world


class Rig:
    """A simulated Jackal on the world's session and a driver for it on the agent's; the ideal device (one odometry
    message per report, world-frame poses) unless ``ideal=False`` (the default device: tests/test_devices_hw_jackal.py)."""

    def __init__(self, sessions, tmp_path, limits: DriverLimits = WIDE, ideal: bool = True, **cfg):
        self.s_agent, self.s_world = sessions
        robot = RobotConfig(id=2, role="follower", pose=(1.0, -2.0, 0.5))
        self.device = JackalDevice(robot, run_dir=tmp_path, session=self.s_world, namespace=f"test{next(_ns)}/robot2",
                                   device={"ideal": ideal})
        self.malformed: list[str] = []
        self.odoms: list = []
        self.driver = JackalDriver(2, limits, session=self.s_agent, on_malformed=self.malformed.append,
                                   on_odom=self.odoms.append, **{"namespace": self.device.namespace, **cfg})
        self.twists: list = []  # what went out on cmd_vel, deserialised by rosbags
        self._sub = None

    def start(self) -> "Rig":
        try:
            self.device.start()
            self.driver.open()  # waits for the device's wall-clock odometry
            self._sub = self.s_world.declare_subscriber(
                self.device.cmd_key, lambda s: self.twists.append(TYPESTORE.deserialize_cdr(s.payload.to_bytes(), TWIST)))
            assert wait_for(lambda: (self.driver.stop(), self.twists)[1], 1.0), "the zero Twists never arrived"
        except BaseException:
            self.close()
            raise
        return self

    def target(self, t: float = 0.0):
        self.device.take_commands(t)
        return self.device.target

    def close(self) -> None:
        self.driver.close()
        if self._sub is not None:
            self._sub.undeclare()
        self.device.close()


@pytest.fixture
def rig(sessions, tmp_path):
    r = Rig(sessions, tmp_path).start()
    yield r
    r.close()


def test_commands_reach_the_device_as_the_same_twist_and_are_kept_alive(sessions, tmp_path):
    clock, wall = FakeClock(), FakeClock()
    rig = Rig(sessions, tmp_path, clock=clock, wall=wall, keepalive_period=0.125).start()
    try:
        rig.driver.command(0.5, 0.3)
        assert wait_for(lambda: rig.target() == (0.5, 0.3)), rig.device.target
        last = rig.twists[-1]
        assert (last.linear.x, last.linear.y, last.linear.z) == (0.5, 0.0, 0.0)
        assert (last.angular.x, last.angular.y, last.angular.z) == (0.0, 0.0, 0.3)
        n, tx = len(rig.twists), rig.driver.counters["tx"]
        clock.run(rig.driver, 0.5, 1 / 16, wall)  # no new command: the keepalive resends it every 0.125 s
        assert rig.driver.counters["tx"] == tx + 4
        assert wait_for(lambda: len(rig.twists) >= n + 4), len(rig.twists) - n  # (and any still on the way)
        assert all((t.linear.x, t.angular.z) == (0.5, 0.3) for t in rig.twists[n:])
    finally:
        rig.close()


def test_commands_are_clamped_to_the_jackal_and_to_the_robot(sessions, tmp_path):
    r = Rig(sessions, tmp_path).start()
    try:
        assert r.driver.command(5.0, -9.0) == (2.0, -4.0)  # robot allows 10: the Jackal's 2.0 / 4.0 bite
        assert wait_for(lambda: r.target() == (2.0, -4.0)), r.device.target
    finally:
        r.close()
    r = Rig(sessions, tmp_path, limits=DriverLimits(v_max=1.0, w_max=4.5)).start()
    try:
        assert r.driver.command(-3.0, 4.4) == (-1.0, 4.0)  # the lower of the two limits, per axis
        assert r.driver.command(math.nan, 1.0) == (0.0, 0.0)
        assert wait_for(lambda: r.twists and (r.twists[-1].linear.x, r.twists[-1].angular.z) == (0.0, 0.0))
    finally:
        r.close()


def test_device_odometry_reaches_read_with_speeds_pose_and_stamp(rig):
    assert rig.odoms, "opening waited for odometry"
    first = rig.driver.read()
    assert first.pose == pytest.approx((1.0, -2.0, 0.5)) and (first.v, first.w) == (0.0, 0.0)  # the world pose
    rig.device.lockstep(0.0)
    body = Body(x=3.0, y=-1.0, yaw=-2.5, v=0.4, w=-0.2)
    rig.device.report(0.1, body)
    stamp = rig.device.device_time(0.1)
    odo = wait_for(lambda: (o := rig.driver.read()) is not None and o.stamp == pytest.approx(stamp) and o)
    assert odo, rig.driver.read()
    assert (odo.v, odo.w, odo.step) == (0.4, -0.2, -1)
    assert odo.pose == pytest.approx((3.0, -1.0, -2.5))
    assert rig.odoms[-1] == odo and rig.driver.fault is None


def test_the_default_device_reports_odometry_from_where_it_booted(sessions, tmp_path):
    """Hardware-like by default: the robot booted at its pose (1, -2, 0.5 rad), so its odometry starts at (0, 0, 0)."""
    r = Rig(sessions, tmp_path, ideal=False).start()
    try:
        assert r.driver.read().pose == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    finally:
        r.close()


def test_device_cmd_timeout_stops_the_body_in_lockstep_time(sessions, tmp_path):
    s_agent, s_world = sessions
    device = JackalDevice(RobotConfig(id=5, role="leader", pose=(0.0, 0.0, 0.0)), run_dir=tmp_path, session=s_world,
                          namespace=f"test{next(_ns)}/robot5", device={"ideal": True})
    device.start()
    device.lockstep(0.0)
    pub = s_agent.declare_publisher(device.cmd_key)
    try:
        def run(steps: int, t0: float, repeat: bool) -> list[tuple[float, float]]:
            out = []
            for k in range(steps):
                t = t0 + 0.1 * k
                if repeat and k:
                    pub.put(encode_twist(1.0, 8.0))
                    assert wait_for(lambda: device._pending)
                device.take_commands(t)
                out.append(device.motion(t + 0.1))
                device.report(t + 0.1, Body(0.0, 0.0, 0.0, *out[-1]))
            return out

        assert wait_for(lambda: (pub.put(encode_twist(1.0, 8.0)), time.sleep(0.02), device._pending)[-1])
        speeds = run(10, 0.0, repeat=False)  # one command, then silence: 1 s of sim time in no wall time at all
        assert device.counters["cmd"] >= 1
        # 20 m/s^2 and 25 rad/s^2 at 50 Hz ticks: v 0.4, 0.8, 1.0, 1.0, 1.0 m/s over the first step;
        # w 0.5, 1.0 ... up to the 4.0 rad/s limit (8.0 was asked for)
        assert speeds[0] == pytest.approx((0.84, 1.5)) and speeds[1] == pytest.approx((1.0, 3.7))
        assert all(s == pytest.approx((1.0, 4.0)) for s in speeds[2:5])
        # the tick after 0.5 s of silence the controller's target is zero: it decelerates at its limits and stops
        assert speeds[5] == pytest.approx((0.36, 3.0)) and speeds[6] == pytest.approx((0.0, 0.6))
        assert speeds[7:] == [(0.0, 0.0)] * 3
        assert device.counters["cmd_timeout"] == 1 and device.target == (0.0, 0.0)
        speeds = run(10, 1.0, repeat=True)  # a command every step: it keeps going
        assert speeds[1] == pytest.approx((0.84, 1.5)) and all(s == pytest.approx((1.0, 4.0)) for s in speeds[3:])
    finally:
        pub.undeclare()
        device.close()


def test_stale_odometry_faults_the_driver_and_sends_zero(sessions, tmp_path):
    """The odometry timeout on the driver's clock, stepped by the test: the clock stands still while the
    last samples arrive, so only the test's steps age them."""
    clock, wall = FakeClock(), FakeClock()
    rig = Rig(sessions, tmp_path, clock=clock, wall=wall, keepalive_period=0.125).start()
    try:
        rig.driver.command(0.5, 0.0)
        assert wait_for(lambda: rig.target() == (0.5, 0.0))
        assert "odometry stopped" in rig.device.fail()  # the device's injected fault: its EKF dies
        assert settle(lambda: rig.driver.counters["odom"])  # what was on the way has arrived
        clock.run(rig.driver, 0.5, 0.125, wall)  # odom_timeout is 0.5 s
        assert rig.driver.fault is None
        clock.run(rig.driver, 0.125, 0.125, wall)
        assert rig.driver.fault == f"no odometry on {rig.device.odom_key} for 0.62 s"
        assert wait_for(lambda: (rig.twists[-1].linear.x, rig.twists[-1].angular.z) == (0.0, 0.0), 0.5)
        assert rig.driver.command(0.5, 0.0) == (0.0, 0.0)  # a faulted driver sends no motion
        assert wait_for(lambda: rig.target() == (0.0, 0.0))  # and the robot's controller has it
        n, tx = len(rig.twists), rig.driver.counters["tx"]
        clock.run(rig.driver, 0.25, 0.125, wall)  # the keepalive goes on: zero, for the controller to hear
        assert rig.driver.counters["tx"] == tx + 2
        assert wait_for(lambda: len(rig.twists) >= n + 2)
        assert all((t.linear.x, t.angular.z) == (0.0, 0.0) for t in rig.twists[n:])
    finally:
        rig.close()


def test_malformed_traffic_is_counted_and_ignored(sessions, tmp_path):
    rig = Rig(sessions, tmp_path, odom_timeout=5.0).start()  # the world does not step here: no stale-odometry fault
    s_world = rig.s_world
    odom_pub = s_world.declare_publisher(rig.driver.odom_key)
    scan_pub = s_world.declare_publisher(rig.driver.scan_key)
    cmd_pub = rig.s_agent.declare_publisher(rig.device.cmd_key)
    try:
        rig.device.lockstep(0.0)
        good = encode_odometry(50.0, 7.0, 8.0, 0.0, 0.1, 0.0)
        assert wait_for(lambda: (odom_pub.put(good), time.sleep(0.01), rig.driver.read().stamp == 50.0)[-1])
        for payload in (b"", b"\xff" * 40, CDR_LE_HEADER + b"\x01", encode_twist(1.0, 1.0),
                        encode_odometry(51.0, 0.0, 0.0, 0.0, math.nan, 0.0)):
            odom_pub.put(payload)
        for payload in (b"junk", encode_odometry(1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                        encode_laserscan(1.0, math.nan, 0.1, 5.0, [1.0]), encode_laserscan(1.0, 0.0, 0.1, 5.0, [])):
            scan_pub.put(payload)
        odom_pub.put(encode_odometry(52.0, 7.0, 8.0, 0.0, 0.2, 0.0))
        scan_pub.put(encode_laserscan(52.0, 0.0, 0.1, 5.0, [1.0, 2.0]))
        assert wait_for(lambda: rig.driver.read().stamp == 52.0 and rig.driver.read_scan() is not None)
        c = rig.driver.counters
        assert (c["odom_not_cdr"], c["odom_undecodable"], c["odom_bad_value"]) == (2, 2, 1), c
        assert (c["scan_not_cdr"], c["scan_undecodable"], c["scan_bad_value"]) == (1, 1, 2), c
        assert sorted(rig.malformed) == sorted(["jackal/odom_not_cdr"] * 2 + ["jackal/odom_undecodable"] * 2
                                               + ["jackal/odom_bad_value", "jackal/scan_not_cdr",
                                                  "jackal/scan_undecodable"] + ["jackal/scan_bad_value"] * 2)
        assert rig.driver.read().v == 0.2 and rig.driver.read_scan().stamp == 52.0 and rig.driver.fault is None
        # and the device's side: a bad command is counted, the good target stays
        rig.driver.command(0.3, 0.1)
        assert wait_for(lambda: rig.target() == (0.3, 0.1))
        for payload in (b"x", encode_odometry(1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                        CDR_LE_HEADER + struct.pack("<6d", math.nan, 0, 0, 0, 0, 0)):
            cmd_pub.put(payload)
        assert wait_for(lambda: (rig.device.take_commands(0.0), rig.device.counters.get("cmd_bad_value"))[-1])
        d = rig.device.counters
        assert (d["cmd_not_cdr"], d["cmd_undecodable"], d["cmd_bad_value"]) == (1, 1, 1), d
        assert rig.device.target == (0.3, 0.1)
    finally:
        for p in (odom_pub, scan_pub, cmd_pub):
            p.undeclare()
        rig.close()


def test_open_without_odometry_fails_naming_the_key(sessions):
    driver = JackalDriver(4, WIDE, session=sessions[0], namespace=f"test{next(_ns)}/nobody", open_timeout=0.2)
    with pytest.raises(DriverError, match=r"no odometry on test\d+/nobody/platform/odom/filtered within 0.2 s"):
        driver.open()
    driver.close()  # never opened: nothing to do, nothing raised


def test_scan_round_trip_through_read_scan(rig):
    assert rig.driver.read_scan() is None
    rig.device.lockstep(2.0)
    ranges = [0.25 * (i % 17) + 0.5 for i in range(180)]
    inc = math.pi / 179
    rig.device.publish_scan(2.5, -math.pi / 2, inc, 5.0, ranges)
    scan = wait_for(lambda: rig.driver.read_scan())
    assert scan is not None, "no scan"
    assert scan.stamp == pytest.approx(rig.device.device_time(2.5), abs=1e-9)
    assert scan.angle_min == pytest.approx(-math.pi / 2, abs=1e-6)
    assert scan.angle_increment == pytest.approx(inc, abs=1e-7) and scan.range_max == 5.0
    assert scan.ranges == pytest.approx(tuple(ranges), abs=1e-6)
    assert rig.driver.counters["scan"] == 1 and rig.device.driver_params()["namespace"] == rig.device.namespace


def test_default_namespace_is_unique_per_fleet(sessions, tmp_path):
    from stack.comm.keys import Keys

    robot = RobotConfig(id=3, role="follower", pose=(0.0, 0.0, 0.0))
    a = JackalDevice(robot, run_dir=tmp_path, session=sessions[1], keys=Keys("fleetA"))
    b = JackalDevice(robot, run_dir=tmp_path, session=sessions[1], keys=Keys("fleetB"))
    assert a.driver_params()["namespace"] == "jackal/fleetA/robot3"
    assert b.cmd_key == "jackal/fleetB/robot3/cmd_vel" and a.cmd_key != b.cmd_key
    assert b.odom_key == "jackal/fleetB/robot3/platform/odom/filtered"
    assert b.scan_key == "jackal/fleetB/robot3/sensors/lidar2d_0/scan"
    with pytest.raises(DeviceError, match="robot 3: jackal driver: namespace"):
        JackalDevice(robot, run_dir=tmp_path, session=sessions[1], namespace="/robot3")
    # the scenario's jackal settings name the topics for driver and device alike
    custom = RobotConfig(id=3, role="follower", pose=(0.0, 0.0, 0.0),
                         driver_params={"jackal": {"cmd_topic": "base/cmd_vel", "namespace": "site/j100_0421"}})
    c = JackalDevice(custom, session=sessions[1], keys=Keys("fleetA"))
    assert c.cmd_key == "jackal/fleetA/robot3/base/cmd_vel"  # our namespace wins: what driver_params() hands over
    with pytest.raises(DeviceError, match="robot 3: jackal driver: unknown|unexpected keyword"):
        JackalDevice(RobotConfig(id=3, role=None, pose=(0.0, 0.0, 0.0), driver_params={"jackal": {"bogus": 1}}),
                     session=sessions[1])


def test_device_odometry_noise_is_seeded(sessions):
    robot = RobotConfig(id=1, role="leader", pose=(0.0, 0.0, 0.0), odom_noise=(0.1, 0.05))
    reported = []
    for _ in range(2):
        d = JackalDevice(robot, session=sessions[1], seed=7, device={"ideal": True})
        d.report(0.1, Body(1.0, 2.0, 0.3, 0.5, 0.2))
        reported.append(d.body)
    assert reported[0] == reported[1] and (reported[0].x, reported[0].y, reported[0].yaw) == (1.0, 2.0, 0.3)
    assert reported[0].v != 0.5 and reported[0].w != 0.2 and abs(reported[0].v - 0.5) < 0.5
