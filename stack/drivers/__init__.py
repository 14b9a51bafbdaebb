"""Drivers behind one interface, chosen by name; backends are imported only when used.

>>> drv = make_driver("sim", robot_id=2, limits=DriverLimits(1.0, 1.0), session=s, keys=Keys("f"))

Each record names the driver class, its settings dataclass (the scenario's ``robot.<driver>`` block,
read by ``Driver._configure``) and the simulated device the world hosts behind it, as strings: the
drivers never import ``stack.sim_bridge``. ``LIDARS``: the lidar sources (sensor drivers).
"""

from __future__ import annotations

from ..plugins import Plugin, PluginError, Registry
from .base import Driver, DriverError, DriverLimits, Odometry

DRIVERS = Registry("drivers", [
    Plugin("sim", None, "stack.drivers.sim:SimDriver", summary="simulated differential drive: cmd_vel / odom over Zenoh"),
    Plugin("can", "stack.drivers.can:CanConfig", "stack.drivers.can:CanDriver",
           device="stack.sim_bridge.devices_can:OdriveDevice", summary="two ODrive axes over CAN (python-can)"),
    Plugin("mavlink", "stack.drivers.mavlink:MavlinkConfig", "stack.drivers.mavlink:MavlinkDriver",
           device="stack.sim_bridge.devices_mavlink:RoverDevice", summary="ArduPilot Rover over MAVLink (pymavlink)"),
    Plugin("jackal", "stack.drivers.jackal:JackalConfig", "stack.drivers.jackal:JackalDriver",
           device="stack.sim_bridge.jackal_sim:JackalDevice", summary="ROS 2 Jackal over Zenoh: zenoh-bridge-ros2dds or rmw_zenoh (CDR)"),
])
BACKENDS = DRIVERS  # python-can's name for it

LIDARS = Registry("lidars", [
    Plugin("world", None, "stack.drivers.lidar:WorldLidar", summary="the simulated world's lidar, on stack/<fleet>/<id>/scan"),
    Plugin("ros2", "stack.drivers.lidar_ros2:Ros2LidarConfig", "stack.drivers.lidar_ros2:Ros2Lidar",
           device="stack.sim_bridge.ros2_lidar_sim:Ros2LidarDevice",
           summary="sensor_msgs/LaserScan from a ROS 2 lidar driver over Zenoh: zenoh-bridge-ros2dds or rmw_zenoh"),
    Plugin("rplidar", "stack.drivers.rplidar:RplidarConfig", "stack.drivers.rplidar:RplidarLidar",
           device="stack.sim_bridge.rplidar_sim:RplidarDevice",
           summary="a Slamtec RPLidar A1/A2 on a serial port (the vendor's protocol, pyserial)"),
])


class UnknownDriver(DriverError):
    pass


def driver_class(name: str) -> type[Driver]:
    try:
        return DRIVERS[name].make()
    except PluginError as e:
        raise UnknownDriver(str(e)) from None


def make_driver(name: str, robot_id: int, limits: DriverLimits, **kw) -> Driver:
    return driver_class(name)(robot_id, limits, **kw)


__all__ = ["BACKENDS", "DRIVERS", "Driver", "DriverError", "DriverLimits", "LIDARS", "Odometry", "UnknownDriver",
           "driver_class", "make_driver"]
