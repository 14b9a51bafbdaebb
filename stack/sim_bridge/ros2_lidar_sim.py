"""A simulated ROS 2 lidar: what a lidar driver node (``urg_node``, ``sick_scan_xd``, ``rplidar_ros``) shows
through zenoh-bridge-ros2dds or rmw_zenoh, the ``ros2`` lidar source's device.

On the world's Zenoh session it publishes ``sensor_msgs/LaserScan`` (CDR, ``stack.drivers.ros2cdr``) on the
robot's scan topic (its ``lidar.ros2`` settings: ``topic``, ``transport``, ``domain_id``, ``ros_distro``; the
namespace is the device's own, ``lidar/<fleet>/robot<id>``, handed to the agent). On ``rmw_zenoh`` it is the
node ``<ns>/lidar_sim`` with a sensor-QoS publisher (samples with rmw_zenoh's attachment).

Each scan is taken at its own time (``rate_hz``, ``jitter_s``, lost with ``drop_prob``:
``device_streams.Stream``) from the sensor's pose then, with its own beam layout (``beams`` over ``fov_deg``,
centred ahead), no return as ``+inf`` (REP 117) or ``range_max``, stamped with the sensor host's clock
(``clock_offset_s`` ahead of the world's).
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from ..drivers.lidar_ros2 import Ros2LidarConfig
from ..drivers.rmw_zenoh import SENSOR_QOS, NodeConfig, RmwZenohNode
from ..drivers.ros2cdr import LASER_SCAN, encode_laserscan
from .device_streams import Stream
from .devices import DeviceError, check_choice, check_number
from .lidar_devices import HostedLidar, LidarDeviceConfig

log = logging.getLogger(__name__)

NODE_NAME = "lidar_sim"


@dataclass(frozen=True)
class Ros2LidarDeviceConfig(LidarDeviceConfig):
    """How the simulated ROS 2 lidar behaves (scenario: the robot's ``lidar.device``)."""

    rate_hz: float = 15.0
    """[Hz] scan rate (Hokuyo UST-10: 40, SICK TiM571: 15, RPLidar A2 via rplidar_ros: 10)."""
    beams: int = 541
    """Beams per scan."""
    fov_deg: float = 270.0
    """[deg] field of view, centred ahead (a TiM571: 270 deg in 0.5 deg steps, 541 beams)."""
    no_return: str = "inf"
    """A beam without a return reads ``inf`` (REP 117) or ``range_max`` (older drivers)."""
    clock_offset_s: float = 0.0
    """[s] how far the sensor host's clock (its header stamps) is ahead of the world's."""
    jitter_s: float = 0.0
    """[s] standard deviation of each scan's time about its nominal tick."""
    drop_prob: float = 0.0
    """Probability that a scan is lost on the way."""

    def __post_init__(self):
        check_number("rate_hz", self.rate_hz, high=1000.0, low_open=True)
        if isinstance(self.beams, bool) or not isinstance(self.beams, int) or not 1 <= self.beams <= 10_000:
            raise ValueError(f"beams must be an integer 1..10000, not {self.beams!r}")
        check_number("fov_deg", self.fov_deg, high=360.0, low_open=True)
        check_choice("no_return", self.no_return, ("inf", "range_max"))
        check_number("clock_offset_s", self.clock_offset_s, low=None)
        check_number("jitter_s", self.jitter_s)
        check_number("drop_prob", self.drop_prob, high=0.99)


class Ros2LidarDevice(HostedLidar):
    """One robot's ROS 2 lidar on the world's Zenoh session (``session`` required)."""

    kind = "ros2"
    config_class = Ros2LidarDeviceConfig

    def __init__(self, robot, **kw):
        super().__init__(robot, **kw)
        if self.session is None:
            raise DeviceError(f"robot {robot.id}: the ros2 lidar device needs the world's zenoh session")
        own = {k: v for k, v in self.params.items() if k != "namespace"}
        self.namespace = self._default_namespace(own.get("transport") == "rmw_zenoh")
        try:
            self.config = Ros2LidarConfig(namespace=self.namespace, **own)
        except (TypeError, ValueError) as e:
            raise DeviceError(f"robot {robot.id}: ros2 lidar device: {e}") from None
        dev = self.device_config
        fov, n = math.radians(dev.fov_deg), dev.beams
        self.angles = np.zeros(1) if n == 1 else np.linspace(-fov / 2, fov / 2, n)
        self.increment = fov / (n - 1) if n > 1 else 0.0
        self.stream = Stream(dev.rate_hz, jitter_s=dev.jitter_s, drop_prob=dev.drop_prob, rng=self.rng)
        self._pub: Any = None
        self._declared: list = []
        self.dropped = 0

    def _default_namespace(self, ros_names: bool) -> str:
        fleet = self.keys.fleet if self.keys is not None else "default"
        if ros_names:
            fleet = re.sub(r"[^A-Za-z0-9_]", "_", fleet)
            fleet = fleet if re.match(r"[A-Za-z_]", fleet) else f"_{fleet}"
        return f"lidar/{fleet}/robot{self.robot_id}"

    def start(self) -> None:
        cfg = self.config
        if cfg.transport == "rmw_zenoh":
            node = RmwZenohNode(self.session, NodeConfig(name=NODE_NAME, namespace=f"/{self.namespace}",
                                                         domain_id=cfg.domain_id, distro=cfg.ros_distro))
            self._declared = [node]
            self._pub = node.publisher(cfg.topic, LASER_SCAN, SENSOR_QOS)
        else:
            self._pub = self.session.declare_publisher(cfg.key(self.robot_id), encoding=zenoh.Encoding.APPLICATION_CDR,
                                                       congestion_control=zenoh.CongestionControl.BLOCK)
            self._declared = [self._pub]

    def driver_params(self) -> dict[str, Any]:
        return {"namespace": self.namespace}

    def lockstep(self, t_sim: float) -> None:
        super().lockstep(t_sim)
        self.stream.restart(t_sim)

    def close(self) -> None:
        while self._declared:
            self._declared.pop().undeclare()
        self._pub = None

    def _emit(self, t0: float, t1: float, pose_at) -> None:
        dev, range_max = self.device_config, float(self.robot.lidar.range)
        for ts, kept in self.stream.due(t1):
            if not kept:
                self.dropped += 1
                continue
            ranges = self.cast(pose_at(max(ts, t0)), self.angles)
            if dev.no_return == "inf":
                ranges = np.where(ranges >= range_max - 1e-6, np.inf, ranges)
            self._pub.put(encode_laserscan(self.host_clock(ts, dev.clock_offset_s), float(self.angles[0]),
                                           self.increment, range_max, ranges, scan_time=1.0 / dev.rate_hz))
            self.scans_sent += 1


__all__ = ["Ros2LidarDevice", "Ros2LidarDeviceConfig"]
