"""``ros2``: ``sensor_msgs/LaserScan`` from any ROS 2 lidar driver (``rplidar_ros``, ``urg_node``,
``sick_scan_xd``...) over Zenoh, without ROS on our side.

Two transports (``transport``), as the ``jackal`` driver has them: ``bridge`` (zenoh-bridge-ros2dds: the
topic ``/<namespace>/<topic>`` is the key ``<namespace>/<topic>``, bare CDR) and ``rmw_zenoh`` (the robot
runs ROS 2's Zenoh middleware: we are the node ``/<namespace>/<node_name>`` with a sensor-QoS
subscription; samples without rmw_zenoh's attachment, or of another type or type hash, are dropped and
counted ``rmw_<kind>``). Payloads are decoded by ``stack.drivers.ros2cdr`` (not CDR, not a LaserScan,
non-finite geometry: counted ``scan_<kind>``, never raised).

Each scan is delivered as a :class:`~stack.drivers.lidar.LidarScan` stamped with its header stamp (the
sending host's clock), its beams at ``angle_min + i * angle_increment``. Opening declares the subscription
and returns: a lidar that sends nothing leaves the agent's scan stale (zero velocity), it does not fail.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass
from typing import Any, Callable, Literal

import numpy as np
import zenoh

from .. import settings
from . import rmw_zenoh
from .lidar import Lidar, LidarError, LidarScan
from .ros2cdr import LASER_SCAN, CdrError, decode_laserscan

log = logging.getLogger(__name__)

_KEY = re.compile(r"[^/*$?#\s]+(/[^/*$?#\s]+)*")


@dataclass(frozen=True)
class Ros2LidarConfig:
    """Where the lidar's ``LaserScan`` topic is on Zenoh."""

    namespace: str | None = None
    """The robot's ROS 2 namespace, without the leading slash (``robot2``); None: ``robot<id>``."""
    topic: str = "scan"
    """The scan topic relative to the namespace (``rplidar_ros`` and ``urg_node``: ``scan``; a Jackal:
    ``sensors/lidar2d_0/scan``)."""
    transport: Literal["bridge", "rmw_zenoh"] = "bridge"
    """``bridge``: zenoh-bridge-ros2dds keys (bare CDR); ``rmw_zenoh``: rmw_zenoh_cpp's keys, attachments and graph."""
    domain_id: int = 0
    """``rmw_zenoh``: the robot's ROS_DOMAIN_ID (0..232)."""
    ros_distro: Literal["jazzy", "humble"] = "jazzy"
    """``rmw_zenoh``: the robot's ROS 2 distribution (type hashes in the keys on Jazzy)."""
    node_name: str = "stack_lidar"
    """``rmw_zenoh``: our node's name in the robot's namespace."""

    def __post_init__(self):
        settings.check(self)
        for name in ("namespace", "topic"):
            value = getattr(self, name)
            if value is not None and not _KEY.fullmatch(value):
                raise ValueError(f"{name}: {value!r} is not a key-expression prefix (chunks separated by '/', "
                                 "no leading or trailing '/', no '*', '$', '?', '#' or spaces)")
        if not 0 <= self.domain_id <= 232:
            raise ValueError(f"domain_id: must be 0..232, got {self.domain_id}")
        if self.transport == "rmw_zenoh":
            try:
                rmw_zenoh.fully_qualified(self.node_config(0).namespace, self.topic)
            except ValueError as e:
                raise ValueError(f"transport: rmw_zenoh needs ROS names: {e}") from None

    def node_config(self, robot_id: int) -> rmw_zenoh.NodeConfig:
        return rmw_zenoh.NodeConfig(name=self.node_name, namespace=f"/{self.namespace or f'robot{robot_id}'}",
                                    domain_id=self.domain_id, distro=self.ros_distro)

    def key(self, robot_id: int) -> str:
        """The scan topic's Zenoh key on this transport."""
        if self.transport == "bridge":
            return f"{self.namespace or f'robot{robot_id}'}/{self.topic}"
        node = self.node_config(robot_id)
        return rmw_zenoh.topic_key(self.domain_id, rmw_zenoh.fully_qualified(node.namespace, self.topic), LASER_SCAN,
                                   self.ros_distro)


class Ros2Lidar(Lidar):
    """A ROS 2 lidar's ``LaserScan`` on the agent's Zenoh session (``session``: the driver never opens one)."""

    name = "ros2"
    config_class = Ros2LidarConfig

    def __init__(self, robot_id: int, config: Ros2LidarConfig | None = None, *, session: zenoh.Session,
                 keys: Any = None, clock: Callable[[], float] = time.monotonic, on_scan=None, on_malformed=None,
                 **params):
        super().__init__(robot_id, clock=clock, on_scan=on_scan, on_malformed=on_malformed)
        self.config = self._configure(config, params)
        if session is None:
            raise LidarError("ros2 lidar: needs the agent's zenoh session")
        self._session = session
        self.key = self.config.key(robot_id)
        self._declared: list = []
        self.node: rmw_zenoh.RmwZenohNode | None = None

    def _open(self) -> None:
        cfg = self.config
        try:
            if cfg.transport == "rmw_zenoh":
                self.node = rmw_zenoh.RmwZenohNode(self._session, cfg.node_config(self.robot_id),
                                                   on_malformed=lambda kind: self.count(f"rmw_{kind}", kind != "lost"))
                self._declared.append(self.node)
                self.node.subscribe(cfg.topic, LASER_SCAN, lambda payload, att: self._payload(payload),
                                    qos=rmw_zenoh.SENSOR_QOS)
            else:
                self._declared.append(self._session.declare_subscriber(
                    self.key, lambda sample: self._payload(sample.payload.to_bytes())))
        except zenoh.ZError as e:
            self._close()
            raise LidarError(f"ros2 lidar {self.robot_id}: cannot subscribe to {self.key}: {e}") from None
        log.info("ros2 lidar %s: LaserScan on %s (%s)", self.robot_id, self.key, cfg.transport)

    def _close(self) -> None:
        self.node = None
        while self._declared:
            self._declared.pop().undeclare()

    def _payload(self, payload: bytes) -> None:
        try:
            data = decode_laserscan(payload)
        except CdrError as e:
            self.count(f"scan_{e.kind}", malformed=True)
            return
        n = len(data.ranges)
        angles = data.angle_min + data.angle_increment * np.arange(n)
        self._deliver(LidarScan(stamp=data.stamp, angles=angles, ranges=np.asarray(data.ranges, float),
                                range_max=data.range_max))


__all__ = ["Ros2Lidar", "Ros2LidarConfig"]
