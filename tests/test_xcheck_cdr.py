"""Cross-check of our ROS 2 CDR (``stack.drivers.ros2cdr``, on rosbags) against ``pycdr2``, the pure
Python CDR of Eclipse Cyclone DDS (``cyclonedds.idl``) that we did not write.

The ROS 2 messages are written here as IDL structs, field by field from their ``.msg`` files
(ROS 2 Humble), with the DDS type names rmw gives them (``geometry_msgs::msg::dds_::Twist_``).
Bytes must be identical both ways, 4-byte encapsulation header and alignment padding included;
strings of every length mod 8 move the padding before each float64 and float32 around.

(No ``from __future__ import annotations`` here: pycdr2 resolves the field types of nested structs
from real annotations.)
"""


import math
import random
from dataclasses import dataclass

import numpy as np
import pytest
from pycdr2 import Endianness, IdlStruct
from pycdr2.types import array, float32, float64, int32, sequence, uint32

from stack.drivers import ros2cdr


# --- builtin_interfaces, std_msgs, geometry_msgs, nav_msgs, sensor_msgs (Humble .msg files) ---
@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3
    angular: Vector3


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose
    covariance: array[float64, 36]


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    twist: Twist
    covariance: array[float64, 36]


@dataclass
class Odometry(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header
    pose: Pose


@dataclass
class LaserScan(IdlStruct, typename="sensor_msgs::msg::dds_::LaserScan_"):
    header: Header
    angle_min: float32
    angle_max: float32
    angle_increment: float32
    time_increment: float32
    scan_time: float32
    range_min: float32
    range_max: float32
    ranges: sequence[float32]
    intensities: sequence[float32]


def f32(x: float) -> float:
    return float(np.float32(x))


def stamp_of(t: float) -> Time:
    ns = round(t * 1e9)
    return Time(ns // 1_000_000_000, ns % 1_000_000_000)


FRAMES = ["", "o", "od", "odo", "odom", "odom1", "odom12", "odom123", "robot3/odom_frame"]  # every length mod 8
rng = random.Random(17)


def twist(v: float, w: float) -> Twist:
    return Twist(Vector3(v, 0.0, 0.0), Vector3(0.0, 0.0, w))


# --- Twist ------------------------------------------------------------------------------------
@pytest.mark.parametrize("v, w", [(0.0, 0.0), (0.5, 1.25), (-1.0, -0.3), (1e-300, 3.141592653589793)])
def test_twist_bytes_identical_both_ways(v, w):
    ours = ros2cdr.encode_twist(v, w)
    theirs = twist(v, w).serialize()
    assert ours[:4] == ros2cdr.CDR_LE_HEADER == theirs[:4] and len(ours) == 4 + 48
    assert ours == theirs
    assert ros2cdr.decode_twist(theirs) == (v, w)
    assert Twist.deserialize(ours) == twist(v, w)


def test_big_endian_cdr_from_another_host_decodes():
    theirs = twist(0.75, -0.5).serialize(endianness=Endianness.Big)
    assert theirs[:4] == b"\x00\x00\x00\x00"  # CDR_BE
    assert ros2cdr.decode_twist(theirs) == (0.75, -0.5)


# --- Odometry ---------------------------------------------------------------------------------
@pytest.mark.parametrize("frame_id, child", [(f, FRAMES[-1 - i]) for i, f in enumerate(FRAMES)])
def test_odometry_bytes_identical_both_ways(frame_id, child):
    t, x, y, yaw = rng.uniform(0, 2e9), rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-math.pi, math.pi)
    v, w = rng.uniform(-1, 1), rng.uniform(-2, 2)
    pcov = [rng.uniform(0, 1) for _ in range(36)]
    tcov = [rng.uniform(0, 1) for _ in range(36)]
    ours = ros2cdr.encode_odometry(t, x, y, yaw, v, w, frame_id=frame_id, child_frame_id=child,
                                   pose_covariance=pcov, twist_covariance=tcov)
    msg = Odometry(Header(stamp_of(t), frame_id), child,
                   PoseWithCovariance(Pose(Point(x, y, 0.0), Quaternion(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))), pcov),
                   TwistWithCovariance(twist(v, w), tcov))
    theirs = msg.serialize()
    assert ours == theirs, (len(ours), len(theirs))
    back = Odometry.deserialize(ours)
    assert back.header == msg.header and back.child_frame_id == child and back.pose.covariance == pcov
    odo = ros2cdr.decode_odometry(theirs)
    assert (odo.v, odo.w) == (v, w) and odo.stamp == pytest.approx(t, abs=1e-9)
    assert odo.pose[:2] == (x, y) and odo.pose[2] == pytest.approx(yaw, abs=1e-12)


# --- PoseStamped (goals from RViz / Nav2 tools; the fleet's slots: stack.agents.ros_graph) -------------
@pytest.mark.parametrize("frame_id", FRAMES)
def test_pose_stamped_bytes_identical_both_ways(frame_id):
    from stack.drivers import rmw_zenoh

    t, x, y, yaw = rng.uniform(0, 2e9), rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-math.pi, math.pi)
    ours = rmw_zenoh.encode_pose_stamped(t, x, y, yaw, frame_id=frame_id)
    msg = PoseStamped(Header(stamp_of(t), frame_id),
                      Pose(Point(x, y, 0.0), Quaternion(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))))
    theirs = msg.serialize()
    assert ours == theirs, (len(ours), len(theirs))
    assert PoseStamped.deserialize(ours) == msg
    p = rmw_zenoh.decode_pose_stamped(theirs)
    assert (p.frame_id, p.x, p.y) == (frame_id, x, y) and p.yaw == pytest.approx(yaw, abs=1e-12)
    assert p.stamp == pytest.approx(t, abs=1e-9)


# --- LaserScan --------------------------------------------------------------------------------
@pytest.mark.parametrize("frame_id, beams", [(f, n) for f, n in zip(FRAMES, [0, 1, 2, 3, 5, 8, 181, 360, 720])])
def test_laserscan_bytes_identical_both_ways(frame_id, beams):
    t = rng.uniform(0, 1e6)
    inc = 2 * math.pi / max(beams, 1)
    ranges = [f32(rng.uniform(0.1, 12.0)) for _ in range(beams)]
    if beams == 0:  # our decoder refuses an empty scan; the encoding must still agree
        ranges = []
    ours = ros2cdr.encode_laserscan(t, -math.pi, inc, 12.0, ranges, range_min=0.05, frame_id=frame_id, scan_time=0.1)
    msg = LaserScan(Header(stamp_of(t), frame_id), f32(-math.pi), f32(-math.pi + inc * max(beams - 1, 0)), f32(inc),
                    0.0, f32(0.1), f32(0.05), 12.0, ranges, [])
    theirs = msg.serialize()
    assert ours == theirs, (len(ours), len(theirs))
    assert LaserScan.deserialize(ours) == msg
    if beams:
        scan = ros2cdr.decode_laserscan(theirs)
        assert scan.ranges == tuple(ranges) and scan.angle_min == f32(-math.pi) and scan.angle_increment == f32(inc)
        assert scan.range_max == 12.0 and scan.stamp == pytest.approx(t, abs=1e-9)


def test_laserscan_from_a_lidar_driver_with_intensities_and_rep117_values():
    """A scan as a ROS 2 lidar driver publishes it: intensities, inf (no return), -inf (too close), NaN."""
    ranges = [1.0, math.inf, -math.inf, math.nan, 30.0, 0.01, 2.5]
    msg = LaserScan(Header(Time(100, 250_000_000), "laser"), f32(-1.5), f32(1.5), f32(0.5), f32(1e-4), f32(0.1),
                    f32(0.15), 12.0, [f32(r) for r in ranges], [f32(i) for i in range(len(ranges))])
    scan = ros2cdr.decode_laserscan(msg.serialize())
    assert scan.stamp == 100.25
    assert scan.ranges == (1.0, 12.0, f32(0.15), 12.0, 12.0, f32(0.15), 2.5)  # REP 117 normalised, as documented

