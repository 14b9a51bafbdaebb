"""The ``mavlink`` robot's device: a simulated ArduPilot Rover autopilot on UDP loopback.

The agent's ``mavlink`` driver connects with ``udpout:127.0.0.1:<port>`` as a companion
computer would to a rover's telemetry port. The rover's controllers (GUIDED targets, speed
and turn-rate ramps, the 3 s target timeout, the FS_GCS hold) decide the body speeds; the
world moves the body and hands the pose back (``set_pose``), with the position noise of the
vehicle's own estimate (the driver's ``position_std``), before the telemetry due goes out.
The rover accelerates like the robot's simulated base (``base.wheel_accel`` x wheel radius).

Its settings (``RoverDeviceConfig``, the robot's ``device:``): ``datum`` places the site on
the globe for GLOBAL_POSITION_INT (both modes; default the scenario's ``site.datum``, which the
world passes as ``site_datum``, else the driver's ``datum`` setting, else ArduPilot SITL's home);
hardware-like (``ideal: false``, the default) the EKF origin is where the rover booted (``ekf_origin: boot``,
as ArduPilot sets it at its first GPS fix), so LOCAL_POSITION_NED is relative to that, not to the site origin; ``SET_GPS_GLOBAL_ORIGIN``
moves it in either mode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..drivers.mavlink import MavlinkConfig
from ..models.geodesy import Datum, check_datum
from .devices import SIM_OPEN_TIMEOUT_S, Body, DeviceConfig, DeviceError, HostedDevice, check_choice
from .rover_sim import SimRover


@dataclass(frozen=True)
class RoverDeviceConfig(DeviceConfig):
    """How the simulated ArduPilot Rover behaves (scenario: the robot's ``device:``)."""

    ekf_origin: str = "boot"
    """``boot``: the EKF origin is where the rover booted (its start pose), LOCAL_POSITION_NED relative to it
    (the hardware); ``site``: the site origin (the datum). Used only with ``ideal: false``; ideal is ``site``."""
    datum: tuple[float, float, float] | None = None
    """(lat [deg], lon [deg], alt [m]) of the site origin, in both modes; None: the scenario's ``site.datum``, else
    the driver's ``datum`` setting, else ArduPilot SITL's default location."""

    def __post_init__(self):
        super().__post_init__()
        check_choice("ekf_origin", self.ekf_origin, ("boot", "site"))
        if self.datum is not None:
            object.__setattr__(self, "datum", check_datum(self.datum))


class RoverDevice(HostedDevice):
    kind = "mavlink"
    config_class = RoverDeviceConfig

    def __init__(self, robot, *, site_datum: Datum | None = None, **kw):
        """``site_datum``: the scenario's ``site.datum`` (the rover's ``datum`` when its settings name none)."""
        super().__init__(robot, site_datum=site_datum, **kw)
        self.config = self.driver_config(MavlinkConfig)
        try:
            site = check_datum(site_datum, "site.datum") if site_datum is not None else None
        except ValueError as e:
            raise DeviceError(f"robot {self.robot_id}: mavlink device: {e}") from None
        self.datum: Datum | None = self.device_config.datum or site or self.config.datum
        """Where the site is on the globe for this rover (None: ArduPilot SITL's home)."""
        self.rng = np.random.default_rng([self.seed, robot.id, 7])
        self.rover: SimRover | None = None
        self._fresh = {"local_position_ned": False, "attitude": False}  # as the driver pairs them into a sample

    def start(self) -> None:
        cfg, b, dev = self.config, self.robot.base, self.device_config
        accel = b.wheel_accel * b.wheel_radius
        try:
            self.rover = SimRover(("127.0.0.1", 0), system=cfg.target_system, component=cfg.target_component,
                                  gcs_system=cfg.source_system, pose=self.robot.pose, integrate_pose=False,
                                  accel_max=accel, yaw_accel_max=2.0 * accel / b.track, clock=self.wall_time,
                                  datum=self.datum, origin_at_boot=not dev.ideal and dev.ekf_origin == "boot")
        except OSError as e:
            raise DeviceError(f"robot {self.robot_id}: cannot bind the rover's UDP port on loopback: {e}") from None
        self.rover.run_realtime()

    def driver_params(self) -> dict:
        return {"connection": f"udpout:127.0.0.1:{self.rover.port}",
                "connect_timeout": max(self.config.connect_timeout, SIM_OPEN_TIMEOUT_S)}

    def fleet_params(self) -> dict:
        """What the fleet hands the agent's driver: the link, and the site's datum where the driver has none of its
        own (the scenario's ``site.datum``, else the rover's, SITL's home: the simulated site is there), so the
        driver places the rover by GLOBAL_POSITION_INT in the site frame whatever its EKF origin; an ideal rover
        without a datum keeps LOCAL_POSITION_NED fixes (its EKF origin is the site's)."""
        own = self.robot.driver_params.get(self.kind, {}).get("datum")
        placed = own is None and (self.datum is not None or not self.device_config.ideal)  # ideal, no datum: as before
        return self.driver_params() | ({"datum": list(self.rover.datum)} if placed else {})

    def take_commands(self, t_sim: float) -> None:
        if self.in_lockstep:
            self.rover.receive(self.device_time(t_sim))
        self.wire_received = self.rover.counters.get("rx", 0)  # every message the driver sent, now handled

    def _restart_timers(self, t_dev: float) -> None:
        self.rover.restart_timers(t_dev)

    def _send_status(self, t_sim: float) -> None:
        """The rover's heartbeat (a driver opening waits for it, then for GUIDED and armed in it)."""
        self.rover.heartbeat()

    def motion(self, t_sim_next: float) -> tuple[float, float]:
        if self.in_lockstep:
            self.rover.advance(self.device_time(t_sim_next))
        return self.rover.body_velocity()

    def report(self, t_sim_next: float, body: Body) -> None:
        nx, ny = self.rng.normal(0.0, self.config.position_std, 2)
        self.rover.set_pose(body.x + nx, body.y + ny, body.yaw, body.v, body.w)
        if self.in_lockstep:
            before = {k: self.rover.counters.get(k, 0) for k in self._fresh}
            self.rover.emit(self.device_time(t_sim_next))
            for k in self._fresh:  # each stream goes out at most once per emit
                self._fresh[k] = self._fresh[k] or self.rover.counters.get(k, 0) > before[k]
            if all(self._fresh.values()):
                self.odom_sent += 1
                self._fresh = dict.fromkeys(self._fresh, False)

    def fail(self) -> str:
        self.rover.force_mode("HOLD")
        return "the rover was switched to HOLD under the driver (a pilot's switch)"

    def _stop_realtime(self) -> None:
        if self.rover is not None:
            self.rover.stop()

    def close(self) -> None:
        if self.rover is not None:
            self.rover.kill()


__all__ = ["RoverDevice", "RoverDeviceConfig"]
