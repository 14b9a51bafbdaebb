"""ROS 2 messages as CDR bytes, without ROS: the payloads zenoh-bridge-ros2dds carries.

Through zenoh-bridge-ros2dds a ROS 2 topic ``/robot2/cmd_vel`` is the Zenoh key
``robot2/cmd_vel`` and its payload is the message's CDR serialisation: a 4-byte
encapsulation header (``00 01 00 00``: CDR, little-endian) and the body. The ``rosbags``
package (its ROS 2 Humble type store) serialises and deserialises them.

The one copy of these conversions: the ``jackal`` driver decodes what a robot sends and
encodes what it commands, and the simulated Jackal (``stack.sim_bridge.jackal_sim``) does
the reverse with the same functions.

Decoding never trusts its input: anything that is not CDR, does not deserialise as the
expected type, or carries non-finite values raises :class:`CdrError` whose ``kind`` names
the counter (``not_cdr``, ``undecodable``, ``bad_value``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from .base import Odometry

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
"""The ROS 2 Humble message definitions (Jackal J100 runs Humble)."""

TWIST = "geometry_msgs/msg/Twist"
ODOMETRY = "nav_msgs/msg/Odometry"
LASER_SCAN = "sensor_msgs/msg/LaserScan"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

CDR_LE_HEADER = b"\x00\x01\x00\x00"
"""Encapsulation header of little-endian plain CDR (what ROS 2 on x86/ARM sends)."""

_T = TYPESTORE.types
_NANO = 1_000_000_000


class CdrError(ValueError):
    """A payload that is not the expected ROS 2 message; ``kind`` is the counter it goes to."""

    def __init__(self, kind: str, what: str):
        super().__init__(what)
        self.kind = kind


@dataclass(frozen=True)
class LaserScanData:
    """A 2D scan: ``ranges[i]`` [m] at ``angle_min + i * angle_increment`` [rad] in the lidar's frame.

    Readings that are not a finite value within the sensor's range (REP 117: ``+inf`` no
    return, ``-inf`` closer than ``range_min``, NaN invalid) are normalised as the stack's
    own scans are: no return or invalid -> ``range_max``, too close -> ``range_min``.
    """

    stamp: float
    angle_min: float
    angle_increment: float
    range_max: float
    ranges: tuple[float, ...]


# --- time ---------------------------------------------------------------------------------
def ros_time(stamp: float):
    """Float seconds -> ``builtin_interfaces/msg/Time`` (sec, nanosec), rounded to the nanosecond."""
    ns = round(stamp * _NANO)
    return _T["builtin_interfaces/msg/Time"](sec=ns // _NANO, nanosec=ns % _NANO)


def _seconds(t) -> float:
    if not 0 <= t.nanosec < _NANO:
        raise CdrError("bad_value", f"stamp nanosec {t.nanosec} out of range")
    return t.sec + t.nanosec * 1e-9


def _header(stamp: float, frame_id: str):
    return _T["std_msgs/msg/Header"](stamp=ros_time(stamp), frame_id=frame_id)


# --- bytes <-> messages -----------------------------------------------------------------
def serialize(msg, typename: str) -> bytes:
    """A message object -> little-endian CDR with its encapsulation header."""
    return bytes(TYPESTORE.serialize_cdr(msg, typename, little_endian=True))


def deserialize(data: bytes | bytearray | memoryview, typename: str):
    """CDR bytes -> a message object of ``typename``; :class:`CdrError` for anything else."""
    data = bytes(data)
    if len(data) < 4 or data[:2] not in (b"\x00\x00", b"\x00\x01"):
        raise CdrError("not_cdr", f"no CDR encapsulation header ({data[:4].hex() or 'empty'})")
    try:
        return TYPESTORE.deserialize_cdr(data, typename)
    except SerdeError as e:
        raise CdrError("undecodable", f"not a {typename}: {e}") from None
    except Exception as e:  # untrusted bytes: whatever the deserialiser trips on is the sender's fault
        raise CdrError("undecodable", f"not a {typename}: {type(e).__name__}: {e}") from None


def _finite(what: str, *values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise CdrError("bad_value", f"{what} is not finite")


def _vector3(x: float = 0.0, y: float = 0.0, z: float = 0.0):
    return _T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))


# --- geometry_msgs/Twist ------------------------------------------------------------------
def twist_msg(v: float, w: float):
    """A planar body velocity as ``geometry_msgs/Twist`` (linear.x, angular.z; the rest zero)."""
    return _T[TWIST](linear=_vector3(v), angular=_vector3(z=w))


def encode_twist(v: float, w: float) -> bytes:
    return serialize(twist_msg(v, w), TWIST)


def decode_twist(data: bytes) -> tuple[float, float]:
    """``geometry_msgs/Twist`` CDR -> (linear.x, angular.z); every component must be finite."""
    m = deserialize(data, TWIST)
    lin, ang = m.linear, m.angular
    _finite("twist", lin.x, lin.y, lin.z, ang.x, ang.y, ang.z)
    return float(lin.x), float(ang.z)


# --- nav_msgs/Odometry --------------------------------------------------------------------
def yaw_quaternion(yaw: float):
    """A rotation about z as ``geometry_msgs/Quaternion``."""
    return _T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


def quaternion_yaw(q) -> float:
    """The yaw (rotation about z, ZYX convention) of a quaternion; it need not be normalised."""
    if not q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w > 1e-12:
        raise CdrError("bad_value", "orientation quaternion is zero")
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), q.w * q.w + q.x * q.x - q.y * q.y - q.z * q.z)


def encode_odometry(stamp: float, x: float, y: float, yaw: float, v: float, w: float, *,
                    frame_id: str = "odom", child_frame_id: str = "base_link",
                    pose_covariance: Sequence[float] | None = None,
                    twist_covariance: Sequence[float] | None = None) -> bytes:
    """A planar pose and body velocity as ``nav_msgs/Odometry`` (frame ``frame_id`` -> ``child_frame_id``)."""
    pose = _T["geometry_msgs/msg/Pose"](position=_T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                        orientation=yaw_quaternion(yaw))
    msg = _T[ODOMETRY](
        header=_header(stamp, frame_id), child_frame_id=child_frame_id,
        pose=_T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=_covariance(pose_covariance)),
        twist=_T["geometry_msgs/msg/TwistWithCovariance"](twist=twist_msg(v, w), covariance=_covariance(twist_covariance)))
    return serialize(msg, ODOMETRY)


def _covariance(values: Sequence[float] | None) -> np.ndarray:
    cov = np.zeros(36, dtype=np.float64) if values is None else np.asarray(values, dtype=np.float64)
    if cov.shape != (36,):
        raise ValueError(f"a covariance has 36 entries (6 x 6, row-major), not {cov.size}")
    return cov


def decode_odometry(data: bytes) -> Odometry:
    """``nav_msgs/Odometry`` CDR -> Odometry(v = twist.linear.x, w = twist.angular.z, stamp = header, pose = (x, y, yaw))."""
    m = deserialize(data, ODOMETRY)
    p, q = m.pose.pose.position, m.pose.pose.orientation
    t = m.twist.twist
    _finite("odometry pose", p.x, p.y, p.z, q.x, q.y, q.z, q.w)
    _finite("odometry twist", t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z)
    return Odometry(v=float(t.linear.x), w=float(t.angular.z), stamp=_seconds(m.header.stamp),
                    pose=(float(p.x), float(p.y), quaternion_yaw(q)))


# --- geometry_msgs/PoseStamped (a motion-capture system's rigid body: vrpn_mocap, mocap4r2) --------------
def encode_pose_stamped(stamp: float, x: float, y: float, yaw: float, *, frame_id: str = "world") -> bytes:
    """A planar pose as ``geometry_msgs/PoseStamped`` in ``frame_id`` (z 0, a rotation about z)."""
    pose = _T["geometry_msgs/msg/Pose"](position=_T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                        orientation=yaw_quaternion(yaw))
    return serialize(_T[POSE_STAMPED](header=_header(stamp, frame_id), pose=pose), POSE_STAMPED)


def decode_pose_stamped(data: bytes) -> tuple[float, float, float, float]:
    """``geometry_msgs/PoseStamped`` CDR -> (stamp, x, y, yaw); every component must be finite."""
    m = deserialize(data, POSE_STAMPED)
    p, q = m.pose.position, m.pose.orientation
    _finite("pose", p.x, p.y, p.z, q.x, q.y, q.z, q.w)
    return _seconds(m.header.stamp), float(p.x), float(p.y), quaternion_yaw(q)


# --- sensor_msgs/LaserScan ----------------------------------------------------------------
def encode_laserscan(stamp: float, angle_min: float, angle_increment: float, range_max: float,
                     ranges: Sequence[float], *, range_min: float = 0.0, frame_id: str = "lidar2d_0_laser",
                     scan_time: float = 0.0) -> bytes:
    """A scan as ``sensor_msgs/LaserScan`` (float32 fields, no intensities); angle_max is the last beam's angle."""
    r = np.asarray(ranges, dtype=np.float32)
    msg = _T[LASER_SCAN](
        header=_header(stamp, frame_id), angle_min=float(angle_min),
        angle_max=float(angle_min + angle_increment * max(len(r) - 1, 0)), angle_increment=float(angle_increment),
        time_increment=0.0, scan_time=float(scan_time), range_min=float(range_min), range_max=float(range_max),
        ranges=r, intensities=np.zeros(0, dtype=np.float32))
    return serialize(msg, LASER_SCAN)


def decode_laserscan(data: bytes) -> LaserScanData:
    """``sensor_msgs/LaserScan`` CDR -> LaserScanData (out-of-range readings normalised, see there)."""
    m = deserialize(data, LASER_SCAN)
    _finite("scan geometry", m.angle_min, m.angle_max, m.angle_increment, m.range_min, m.range_max)
    if not 0.0 <= m.range_min < m.range_max:
        raise CdrError("bad_value", f"scan range limits {m.range_min:g}..{m.range_max:g}")
    if len(m.ranges) == 0:
        raise CdrError("bad_value", "scan without ranges")
    r = np.asarray(m.ranges, dtype=np.float64)
    r = np.where(np.isnan(r) | (r > m.range_max), m.range_max, np.maximum(r, m.range_min))
    return LaserScanData(stamp=_seconds(m.header.stamp), angle_min=float(m.angle_min),
                         angle_increment=float(m.angle_increment), range_max=float(m.range_max),
                         ranges=tuple(r.tolist()))


__all__ = ["CDR_LE_HEADER", "CdrError", "LASER_SCAN", "LaserScanData", "ODOMETRY", "TWIST", "decode_laserscan",
           "decode_odometry", "decode_twist", "deserialize", "encode_laserscan", "encode_odometry", "encode_twist",
           "quaternion_yaw", "ros_time", "serialize", "twist_msg", "yaw_quaternion"]
