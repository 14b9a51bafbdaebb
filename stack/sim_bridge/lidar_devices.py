"""Simulated lidars the world hosts behind a robot's lidar source (``robot.lidar.source``: ``ros2``,
``rplidar``), so that the agent's real sensor driver reads them (``stack/drivers/lidar*.py``, ``rplidar.py``).

A hosted lidar scans at its own rate and times, not once per world step: each world step the world calls
``report(t0, t1, before, after)`` with the body before and after the step, and the device sends every scan
(or every sample, for a spinning RPLidar) taken in (t0, t1], each cast by the world (``ray_caster``, i.e.
``World.lidar_at``) from the sensor's pose at its own time: on the arc the world moved the body along, with
the robot's ``lidar.mount`` (the sensor's pose on the robot). ``scans_sent`` counts the whole scans sent,
as the driver assembles them: the world's clock carries it (``Clock.device_scans``), so a lock-step agent
knows when it has all of a step's scans. ``report`` runs in both modes (lock-step: sim time; real time: a
world step of wall time, the step's scans at its end). Stamps are the sensor host's clock: sim time in
lock-step, the epoch in real time, plus the device's ``clock_offset_s`` where it has one.

Settings: the robot's ``lidar.device`` mapping (simulation only), checked against the device's
``config_class``; unknown keys and bad values are a one-line ``DeviceError`` naming the robot.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from .device_streams import arc
from .devices import Body, DeviceConfig, DeviceError


@dataclass(frozen=True)
class LidarDeviceConfig:
    """What every simulated lidar's settings have (subclassed per device; the robot's ``lidar.device``)."""

    from_settings = classmethod(DeviceConfig.from_settings.__func__)


class HostedLidar(ABC):
    """One simulated lidar on one robot. ``session``/``keys``: the world's (Zenoh-carried sensors)."""

    kind = "base"
    config_class: type = LidarDeviceConfig

    def __init__(self, robot, *, session: Any = None, keys: Any = None, seed: int = 0,
                 device: Mapping[str, Any] | None = None):
        self.robot, self.robot_id = robot, robot.id
        self.session, self.keys, self.seed = session, keys, seed
        lid = robot.lidar
        settings = device if device is not None else lid.device
        try:
            self.device_config = self.config_class.from_settings(settings)
        except ValueError as e:
            raise DeviceError(f"robot {robot.id}: {self.kind} lidar device: {e}") from None
        self.params = dict(lid.params)  # the source's settings, as the agent's driver reads them
        self.mount = tuple(lid.mount)
        self.ray_caster: Callable[..., np.ndarray] | None = None
        """``(x, y, yaw, angles) -> ranges``: the world's rays from a sensor at that world pose."""
        self.rng = np.random.default_rng([seed, robot.id, 0x1D])
        self.scans_sent = 0
        self.in_lockstep = False

    # --- what the world calls ------------------------------------------------------------
    @abstractmethod
    def start(self) -> None:
        """Make the endpoint (a pty, the Zenoh publisher) before the world announces itself."""

    @abstractmethod
    def driver_params(self) -> dict[str, Any]:
        """The settings the agent's lidar source needs to find this device (``{"port": ...}``)."""

    def lockstep(self, t_sim: float) -> None:
        """From here sim time is the device's clock."""
        self.in_lockstep = True

    def report(self, t0: float, t1: float, before: Body, after: Body) -> None:
        """The world moved the body from ``before`` (at ``t0``) to ``after`` (at ``t1``): send what the sensor
        took in (t0, t1]."""
        start = (before.x, before.y, before.yaw)
        self._emit(t0, t1, lambda t: arc(start, after.v, after.w, t - t0))

    @abstractmethod
    def _emit(self, t0: float, t1: float, pose_at: Callable[[float], tuple[float, float, float]]) -> None:
        """Send the scans (samples) taken in (t0, t1]; ``pose_at(t)``: the body's world pose at ``t``."""

    @abstractmethod
    def close(self) -> None:
        """The device is gone."""

    # --- helpers ---------------------------------------------------------------------------
    def sensor_pose(self, body: tuple[float, float, float]) -> tuple[float, float, float]:
        """The sensor's world pose on a body at ``body``: the body's pose times the mount."""
        x, y, yaw = body
        mx, my, myaw = self.mount
        c, s = math.cos(yaw), math.sin(yaw)
        return x + c * mx - s * my, y + s * mx + c * my, yaw + myaw

    def cast(self, body: tuple[float, float, float], angles: np.ndarray) -> np.ndarray:
        """Ranges [m] at ``angles`` (sensor frame) from the sensor on a body at ``body``; a reading at the
        world's range (the robot's ``lidar.range``) is no return."""
        if self.ray_caster is None:
            raise DeviceError(f"robot {self.robot_id}: {self.kind} lidar device has no ray caster")
        return np.asarray(self.ray_caster(*self.sensor_pose(body), np.asarray(angles, float)), float)

    def host_clock(self, t_sim: float, offset_s: float = 0.0) -> float:
        """The sensor host's clock at sim time ``t_sim``: sim time in lock-step, the epoch in real time."""
        return (t_sim if self.in_lockstep else time.time()) + offset_s


def lidar_device_class(source: str) -> type[HostedLidar]:
    """The simulated device behind lidar source ``source`` (its ``LIDARS`` record), imported now."""
    from ..drivers import LIDARS

    rec = LIDARS.get(source)
    if rec is None or rec.device is None:
        raise DeviceError(f"no simulated device for lidar source {source!r}")
    return rec.device_class()


def make_lidar_device(robot, **kw) -> HostedLidar:
    return lidar_device_class(robot.lidar.source)(robot, **kw)


__all__ = ["HostedLidar", "LidarDeviceConfig", "lidar_device_class", "make_lidar_device"]
