"""Simulated devices hosted by the world: the hardware a driver talks to, bound to one robot's body.

A robot whose driver is not ``sim`` gets a device here that speaks the real protocol: an
ODrive pair behind an slcan adapter on a pseudo-terminal (``can``), an ArduPilot Rover
autopilot on UDP loopback (``mavlink``), a ROS 2 Jackal behind zenoh-bridge-ros2dds
(``jackal``). The agent's driver is the code that drives the real hardware; only what is
behind the wire is simulated. The device, not the world, decides how the body moves: the
world integrates the body with the device's ``motion`` and tells the device back where the
body went (``report``), so the device's telemetry describes the simulated body.

Lifecycle, driven by the world (``WorldServer``):

1. ``start()`` before the world announces itself: the endpoint exists (the pty link, the
   UDP port, the Zenoh keys) and the device runs on the wall clock, so the agents' drivers
   can open it (handshakes, arming) while the world waits for their liveliness tokens.
2. ``lockstep(t_sim)`` when lock-step stepping begins (not called in real time): the
   device stops its wall-clock thread; from here its time is its own start offset plus the
   sim time (monotonic across the handover).
3. Each step k (lock-step and real time alike), after the step's commands are in:
   ``take_commands(t_k)`` handles what the driver sent so far; ``motion(t_k + dt)`` advances
   the device's actuators to the end of the step and returns the body speeds (v, w) the
   world moves the body with over the step; the world steps; ``report(t_k + dt, body)``
   gives the device the body's pose and speeds at the end of the step and sends whatever
   telemetry is due by then (before the world publishes step k+1's sensors). ``odom_sent`` counts the
   odometry samples the device has sent, as its driver assembles them (one per pair of encoder frames, per
   position + attitude pair, per ``Odometry`` message): the world's clock tells each agent how many there
   were, so an agent knows when it has step k's (``stack.comm.lockstep``; device wires carry no step).
   In real time the device's own thread keeps handling traffic as it arrives, and these
   calls only sync the body.
4. ``close()``: the device is gone (the endpoint disappears).

Devices are made by name from ``DEVICES`` (lazy imports, like the drivers' registry).
``driver_params(robot_id)`` tells the fleet what to hand the agent's driver so that it finds
the device (merged over the scenario's own driver settings for that robot).
"""

from __future__ import annotations

import importlib
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any


SIM_OPEN_TIMEOUT_S = 10.0
"""[s] at least this long for a driver to open its simulated device: the whole fleet (router, world with
every device, all agents) starts at once on one machine, so handshakes take longer than on a robot."""


@dataclass(frozen=True)
class Body:
    """A robot body as the world moved it: pose in the world frame and body speeds."""

    x: float
    y: float
    yaw: float
    v: float
    w: float


class DeviceError(RuntimeError):
    """A device that cannot be hosted (bad settings, an endpoint that cannot be made)."""


class HostedDevice(ABC):
    """One simulated device behind one robot's driver."""

    kind = "base"

    def __init__(self, robot, *, run_dir: Path | None = None, session: Any = None, keys: Any = None, seed: int = 0):
        self.robot = robot
        self.robot_id = robot.id
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.session = session
        self.keys = keys
        self.seed = seed
        self._wall0 = time.monotonic()
        self._offset: float | None = None  # device time = offset + sim time, once in lock-step
        self.odom_sent = 0  # odometry samples sent, as the driver assembles them (the lock-step clock counts them)

    def driver_config(self, cls, **over):
        """The robot's ``<driver>:`` settings as its driver reads them (``cls``: that driver's config
        dataclass), so device and driver agree on the robot (wheels, node ids, system ids, topics)."""
        try:
            return cls(**(dict(self.robot.driver_params.get(self.kind, {})) | over))
        except (TypeError, ValueError) as e:
            raise DeviceError(f"robot {self.robot_id}: {e}") from None

    # --- time ----------------------------------------------------------------------------
    def wall_time(self) -> float:
        """Device time while it runs on the wall clock (from its start)."""
        return time.monotonic() - self._wall0

    def device_time(self, t_sim: float) -> float:
        """Device time of a sim time (lock-step), or the wall time (real time)."""
        return self.wall_time() if self._offset is None else self._offset + t_sim

    @property
    def in_lockstep(self) -> bool:
        return self._offset is not None

    def lockstep(self, t_sim: float) -> None:
        """From now on the world's sim time drives the device (stops the wall-clock thread)."""
        self._stop_realtime()
        self._offset = self.wall_time() - t_sim

    # --- what the world calls -------------------------------------------------------------
    @abstractmethod
    def start(self) -> None:
        """Make the endpoint and run on the wall clock until ``lockstep``."""

    @abstractmethod
    def driver_params(self) -> dict[str, Any]:
        """Settings the agent's driver needs to find this device (e.g. ``{"channel": ...}``)."""

    @abstractmethod
    def take_commands(self, t_sim: float) -> None:
        """Handle every message the driver has sent so far (they act from ``t_sim`` on)."""

    @abstractmethod
    def motion(self, t_sim_next: float) -> tuple[float, float]:
        """Advance the actuators to ``t_sim_next``; the body speeds (v [m/s], w [rad/s]) over the step."""

    @abstractmethod
    def report(self, t_sim_next: float, body: Body) -> None:
        """The body as the world moved it at ``t_sim_next``; send the telemetry due by then."""

    def publish_scan(self, t_sim: float, angle_min: float, angle_increment: float, range_max: float,
                     ranges) -> None:
        """The world's lidar scan at ``t_sim``, for a device that carries the robot's lidar on its own wire
        (a bridged ROS 2 robot publishes ``LaserScan``); the others have nothing to do."""

    @abstractmethod
    def fail(self) -> str:
        """Inject this device's typical failure (``--device-fault``); returns what happened, in words."""

    @abstractmethod
    def _stop_realtime(self) -> None:
        """Stop the wall-clock thread (idempotent)."""

    @abstractmethod
    def close(self) -> None:
        """The device is gone: nothing more on its wire."""


# name -> "module:Class", imported when a robot needs it
DEVICES: dict[str, str] = {
    "can": "stack.sim_bridge.devices_can:OdriveDevice",
    "mavlink": "stack.sim_bridge.devices_mavlink:RoverDevice",
    "jackal": "stack.sim_bridge.jackal_sim:JackalDevice",
}


def device_class(driver: str) -> type[HostedDevice]:
    if driver not in DEVICES:
        raise DeviceError(f"no simulated device for driver {driver!r} (the world hosts {', '.join(sorted(DEVICES))})")
    module, cls = DEVICES[driver].split(":")
    return getattr(importlib.import_module(module), cls)


def make_device(driver: str, robot, **kw) -> HostedDevice:
    return device_class(driver)(robot, **kw)


__all__ = ["Body", "DEVICES", "DeviceError", "HostedDevice", "device_class", "make_device"]
