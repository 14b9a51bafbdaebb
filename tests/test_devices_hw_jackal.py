"""The simulated Jackal with hardware-like settings (``device: {ideal: false, ...}``).

Each test runs the device in lock-step on a real Zenoh session and reads its wire with
``rosbags`` (deserialising the CDR as a ROS 2 node would), never through our decoders:
rates counted over sim time, the odom frame from boot, the robot's clock in the stamps,
scans at their own times and poses.
"""

from __future__ import annotations

import itertools
import math
import threading

import numpy as np
import pytest

from conftest import wait_for
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session
from stack.drivers.ros2cdr import LASER_SCAN, ODOMETRY, TYPESTORE
from stack.scenario import LidarConfig, RobotConfig
from stack.sim_bridge.devices import Body, DeviceError
from stack.sim_bridge.jackal_sim import JackalDevice, JackalDeviceConfig

_ns = itertools.count()
BOOT = (2.0, -1.0, math.radians(30.0))
DT = 0.1


@pytest.fixture(scope="module")
def sessions():
    ep = free_tcp_endpoint()
    with open_session(SessionConfig(mode="router", listen=[ep])), \
            open_session(SessionConfig(connect=[ep])) as s_agent, \
            open_session(SessionConfig(connect=[ep])) as s_world:
        yield s_agent, s_world


class Wire:
    """The device's odometry and scans as a ROS 2 node receives them (rosbags deserialisation)."""

    def __init__(self, session, device):
        self.odom: list = []
        self.scan: list = []
        self._lock = threading.Lock()
        self._subs = [session.declare_subscriber(device.odom_key, lambda s: self._add(self.odom, s, ODOMETRY)),
                      session.declare_subscriber(device.scan_key, lambda s: self._add(self.scan, s, LASER_SCAN))]
        assert wait_for(lambda: self.odom, 3.0), "the wall-clock odometry never came: the subscription is not up"

    def _add(self, into: list, sample, kind: str) -> None:
        with self._lock:
            into.append(TYPESTORE.deserialize_cdr(sample.payload.to_bytes(), kind))

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def lockstep_only(msgs: list) -> list:
    """The samples stamped on sim time (the wall-clock thread stamps with the epoch)."""
    return [m for m in list(msgs) if stamp(m) < 100.0]


def yaw_of(msg) -> float:
    q = msg.pose.pose.orientation
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def in_boot_frame(x: float, y: float, yaw: float) -> tuple[float, float, float]:
    """Our own copy of odom <- site for the boot pose (independent of the device's code)."""
    bx, by, byaw = BOOT
    c, s = math.cos(byaw), math.sin(byaw)
    dx, dy = x - bx, y - by
    return c * dx + s * dy, -s * dx + c * dy, math.atan2(math.sin(yaw - byaw), math.cos(yaw - byaw))


def drive(device, steps: int, v: float, w: float, scans: bool = True) -> list[Body]:
    """Lock-step the device as the world does: the body on a constant (v, w) arc from BOOT, Euler-free (exact)."""
    device.lockstep(0.0)
    x, y, yaw = BOOT
    bodies = [Body(x, y, yaw, 0.0, 0.0)]
    device.report(0.0, bodies[0])
    for k in range(steps):
        t = k * DT
        if scans:
            device.publish_scan(t, -math.pi / 2, math.pi / 179, 5.0, np.full(180, 2.0 + t))
        device.take_commands(t)
        device.motion(t + DT)
        if abs(w) > 1e-12:
            x, y = x + v / w * (math.sin(yaw + w * DT) - math.sin(yaw)), y - v / w * (math.cos(yaw + w * DT) - math.cos(yaw))
        yaw += w * DT
        bodies.append(Body(x, y, yaw, v, w))
        device.report(t + DT, bodies[-1])
    return bodies


def make(sessions, **settings) -> JackalDevice:
    robot = RobotConfig(id=4, role="leader", pose=BOOT, lidar=LidarConfig(beams=180, fov=math.pi, range=5.0))
    dev = JackalDevice(robot, session=sessions[1], namespace=f"hw{next(_ns)}/robot4",
                       device={"ideal": False, **settings})
    dev.start()
    return dev


def test_odometry_at_50_hz_in_the_odom_frame_from_boot_with_the_robots_clock(sessions):
    dev = make(sessions, clock_offset_s=3.7, lidar_rate_hz=15.0)
    wire = Wire(sessions[0], dev)
    try:
        bodies = drive(dev, 10, v=0.5, w=0.3)
        assert wait_for(lambda: len(lockstep_only(wire.odom)) >= 51 and len(lockstep_only(wire.scan)) >= 15, 3.0)
        lockstep = lockstep_only(wire.odom)  # the wall-clock thread's (epoch-stamped) samples came first
        stamps = np.array([stamp(m) for m in lockstep])
        assert len(lockstep) == 51  # 1 s of sim time at 50 Hz, both ends: 5 per 0.1 s step
        assert stamps == pytest.approx(3.7 + 0.02 * np.arange(51), abs=1e-6)
        first = lockstep[0].pose.pose.position
        assert (first.x, first.y, yaw_of(lockstep[0])) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)  # boot: origin
        for m, body in zip(lockstep[::5], bodies):  # every fifth sample is at a step's end
            p = m.pose.pose.position
            assert (p.x, p.y, yaw_of(m)) == pytest.approx(in_boot_frame(body.x, body.y, body.yaw), abs=1e-5)
        mid = lockstep[2].pose.pose.position  # t = 0.04: inside the first step, on its arc
        x, y, yaw = in_boot_frame(*arc_from_boot(0.5, 0.3, 0.04))
        assert (mid.x, mid.y, yaw_of(lockstep[2])) == pytest.approx((x, y, yaw), abs=1e-6)
        assert lockstep[-1].twist.twist.linear.x == pytest.approx(0.5) and lockstep[0].header.frame_id == "odom"
        scans = lockstep_only(wire.scan)
        assert len(scans) == 15  # 15 Hz over [0, 1): 0, 1/15, ..., 14/15
        assert [stamp(m) for m in scans] == pytest.approx([3.7 + i / 15 for i in range(15)], abs=1e-6)
        assert scans[0].scan_time == pytest.approx(1 / 15)
    finally:
        wire.close()
        dev.close()


def arc_from_boot(v: float, w: float, t: float) -> tuple[float, float, float]:
    x, y, yaw = BOOT
    return x + v / w * (math.sin(yaw + w * t) - math.sin(yaw)), y - v / w * (math.cos(yaw + w * t) - math.cos(yaw)), yaw + w * t


def test_scans_are_cast_at_their_own_time_and_pose_with_their_own_layout(sessions):
    dev = make(sessions, lidar_rate_hz=15.0, lidar_beams=271, lidar_fov_deg=270.0)
    cast: list[tuple[float, float, float, int]] = []

    def caster(x, y, yaw, angles):
        cast.append((x, y, yaw, len(angles)))
        r = np.full(len(angles), 5.0)  # nothing in range ...
        r[len(angles) // 2] = 1.25  # ... but straight ahead
        return r

    dev.ray_caster = caster
    wire = Wire(sessions[0], dev)
    try:
        drive(dev, 2, v=0.5, w=0.3)
        assert wait_for(lambda: len(lockstep_only(wire.scan)) >= 3, 3.0)
        scans = lockstep_only(wire.scan)
        assert [round(stamp(m) * 15) for m in scans] == [0, 1, 2]  # 0, 1/15, 2/15 in [0, 0.2)
        assert cast[1][:3] == pytest.approx(arc_from_boot(0.5, 0.3, 1 / 15), abs=1e-9)  # the pose at 1/15 s
        assert all(n == 271 for *_, n in cast)
        s = scans[1]
        assert len(s.ranges) == 271 and s.angle_min == pytest.approx(-math.radians(135), abs=1e-6)
        assert s.angle_increment == pytest.approx(math.radians(1.0), abs=1e-6)
        assert s.ranges[135] == pytest.approx(1.25) and np.isinf(s.ranges[0]) and np.isinf(s.ranges[-1])  # REP 117
    finally:
        wire.close()
        dev.close()


def test_without_a_caster_scans_reuse_the_worlds_newest_scan_resampled(sessions):
    dev = make(sessions, lidar_rate_hz=10.0, lidar_beams=361, lidar_fov_deg=360.0, no_return="range_max")
    wire = Wire(sessions[0], dev)
    try:
        drive(dev, 3, v=0.2, w=0.1)
        assert wait_for(lambda: len(lockstep_only(wire.scan)) >= 3, 3.0)
        s = lockstep_only(wire.scan)[2]  # t = 0.2: the world's scan of that step (2.2 m everywhere)
        r = np.asarray(s.ranges)
        ahead = r[120:241]  # the world's 180 deg field of view
        assert np.allclose(ahead, 2.2, atol=1e-5)
        assert np.allclose(r[:60], 5.0) and np.allclose(r[-60:], 5.0)  # behind: outside it, no return = range_max
    finally:
        wire.close()
        dev.close()


def test_losses_and_jitter_are_seeded_and_bounded(sessions):
    def run():
        dev = make(sessions, drop_prob=0.3, jitter_s=0.004, odom_frame="site")
        wire = Wire(sessions[0], dev)
        try:
            drive(dev, 10, v=0.5, w=0.0, scans=False)
            sent = dev.hardware.odom.sent
            assert wait_for(lambda: len(lockstep_only(wire.odom)) >= sent, 3.0)
            return dev.hardware.odom.dropped, sent, [stamp(m) for m in lockstep_only(wire.odom)], wire.odom[-1]
        finally:
            wire.close()
            dev.close()

    (dropped, sent, stamps, last), (dropped2, _, stamps2, _) = run(), run()
    assert dropped == dropped2 and stamps == stamps2  # the same seed: the same losses and jitter
    assert 5 <= dropped <= 30 and len(stamps) == sent and sent + dropped in (50, 51)  # the last may be jittered late
    ticks = np.array(stamps) / 0.02
    assert np.all(np.abs(ticks - np.rint(ticks)) <= 0.45 + 1e-6) and np.any(np.abs(ticks - np.rint(ticks)) > 0.01)
    assert np.all(np.diff(stamps) > 0)
    p = last.pose.pose.position
    t = stamp(last)
    assert (p.x, p.y) == pytest.approx((BOOT[0] + 0.5 * t * math.cos(BOOT[2]), BOOT[1] + 0.5 * t * math.sin(BOOT[2])),
                                       abs=1e-6)  # odom_frame: site


def test_ideal_sends_one_world_frame_sample_per_step_and_hardware_like_is_the_default(sessions):
    robot = RobotConfig(id=4, role="leader", pose=BOOT)
    assert not JackalDevice(robot, session=sessions[1], namespace=f"hw{next(_ns)}/robot4").device_config.ideal
    assert JackalDeviceConfig().lidar_rate_hz == 25.0 and JackalDeviceConfig().odom_rate_hz == 50.0
    dev = JackalDevice(robot, session=sessions[1], namespace=f"hw{next(_ns)}/robot4", device={"ideal": True})
    assert dev.device_config.ideal and dev.hardware is None
    dev.start()
    wire = Wire(sessions[0], dev)
    try:
        dev.lockstep(0.0)
        n0 = len(wire.odom)
        dev.report(0.1, Body(*BOOT, 0.0, 0.0))
        assert wait_for(lambda: len(wire.odom) > n0)
        p = wire.odom[-1].pose.pose.position
        assert (p.x, p.y) == pytest.approx(BOOT[:2])
    finally:
        wire.close()
        dev.close()


@pytest.mark.parametrize("settings, field", [
    ({"odom_rate_hz": 0}, "odom_rate_hz"), ({"lidar_rate_hz": -3}, "lidar_rate_hz"), ({"odom_frame": "map"}, "odom_frame"),
    ({"lidar_beams": 2.5}, "lidar_beams"), ({"lidar_fov_deg": 400}, "lidar_fov_deg"), ({"drop_prob": 1.0}, "drop_prob"),
    ({"clock_offset_s": math.inf}, "clock_offset_s"), ({"jitter_s": -1}, "jitter_s"), ({"ideal": "no"}, "ideal"),
    ({"bogus": 1}, "bogus"), ({"no_return": "nan"}, "no_return"),
])
def test_bad_settings_are_one_line_errors_naming_the_field(sessions, settings, field):
    robot = RobotConfig(id=4, role="leader", pose=BOOT)
    with pytest.raises(DeviceError, match=rf"robot 4: jackal device: .*{field}") as e:
        JackalDevice(robot, session=sessions[1], namespace="x/robot4", device=settings)
    assert "\n" not in str(e.value)
    assert JackalDeviceConfig.from_settings({"ideal": False}).odom_rate_hz == 50.0
