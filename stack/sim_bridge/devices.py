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
   device stops its wall-clock thread; from here its time is ``LOCKSTEP_EPOCH`` plus the sim
   time, the same numbers in every run (monotonic across the handover: the wall-clock phase is
   shorter), and every timer it holds (heartbeat and sample schedules, watchdogs, target and
   failsafe ages) starts again at the handover (``_restart_timers``): nothing the wall-clock
   phase did (how long it lasted, at which phase its ticks fell) shows in a lock-step run.
3. Each step k (lock-step and real time alike), after the step's commands are in:
   ``take_commands(t_k)`` handles what the driver sent so far (lock-step: the world calls it
   until ``wire_received`` counts every message the driver had put on the wire when it
   answered step k, ``stack.comm.lockstep.DeviceWires``); ``motion(t_k + dt)`` advances
   the device's actuators to the end of the step and returns the body speeds (v, w) the
   world moves the body with over the step; the world steps; ``report(t_k + dt, body)``
   gives the device the body's pose and speeds at the end of the step and sends whatever
   telemetry is due by then (before the world publishes step k+1's sensors). ``odom_sent`` counts the
   odometry samples the device has sent, as its driver assembles them (one per pair of encoder frames, per
   position + attitude pair, per ``Odometry`` message): the world's clock tells each agent how many there
   were, so an agent knows when it has step k's (``stack.comm.lockstep``; device wires carry no step).
   In real time the device's own thread keeps handling traffic as it arrives, and these
   calls only sync the body.
4. ``serve(t)`` while a lock-step world stands still at ``t`` (a restarted agent opening its driver, the
   agents leaving after the run): the device handles what its driver sends (a rover ACKs GUIDED, arming,
   HOLD), repeats its status (heartbeats, odometry standing still), and no time passes.
5. ``close()``: the device is gone (the endpoint disappears).

Each device has a typed config (``config_class``, a ``DeviceConfig``): how real the device is.
``ideal: false`` (the default) does what real hardware does (the device's own frames, rates,
clock and losses; see each device's config), so what passes here is what drives a real robot;
``ideal: true`` keeps the kind simulator (world-frame odometry, one sample per step) for
comparisons. The robot's ``odom_origin: auto`` follows (``boot`` for a hardware-like device). The settings come from the robot's
``device:`` mapping in the scenario (``device=`` here overrides it); unknown keys and bad
values are a one-line ``DeviceError`` naming the robot and the field.

Devices are made by driver name from the drivers' registry (each record names its device; lazy imports).
``driver_params(robot_id)`` tells the fleet what to hand the agent's driver so that it finds
the device (merged over the scenario's own driver settings for that robot).
"""

from __future__ import annotations

import dataclasses
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping


LOCKSTEP_EPOCH = 65536.0
"""[s] a device's time when lock-step begins (sim time 0): a constant, so device times (and every sum and difference
of them) are the same floating-point numbers in every run; a power of two, 18 h, longer than any wall-clock phase."""

SERVE_STATUS_S = 0.05
"""[s] (wall) how often a device standing still in lock-step (``serve``) repeats its status: a heartbeat's period."""

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


@dataclass(frozen=True)
class DeviceConfig:
    """What every simulated device's settings have (subclassed per device)."""

    ideal: bool = False
    """False (the default): behave as the hardware does; True: the kind simulator (world-frame odometry, one sample
    per step; the other settings are not used), for comparisons."""

    def __post_init__(self):
        if not isinstance(self.ideal, bool):
            raise ValueError(f"ideal must be true or false, not {self.ideal!r}")

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any] | None):
        """The config from a scenario mapping; unknown keys and bad values raise a one-line ValueError."""
        settings = dict(settings or {})
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(settings) - names)
        if unknown:
            raise ValueError(f"unknown setting(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})")
        try:
            return cls(**settings)
        except TypeError as e:  # a wrongly typed value the checks below did not name
            raise ValueError(str(e)) from None


def check_number(name: str, value: Any, *, low: float | None = 0.0, high: float | None = None,
                 low_open: bool = False) -> None:
    """A finite real number within [low, high] (``low_open``: > low), else a one-line ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, not {value!r}")
    if low is not None and (value <= low if low_open else value < low):
        raise ValueError(f"{name} must be {'>' if low_open else '>='} {low:g}, not {value!r}")
    if high is not None and value > high:
        raise ValueError(f"{name} must be <= {high:g}, not {value!r}")


def check_choice(name: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(choices)}, not {value!r}")


class HostedDevice(ABC):
    """One simulated device behind one robot's driver.

    ``device``: the device's settings (``config_class`` fields); default the robot's ``device``
    mapping from the scenario, if it has one.
    """

    kind = "base"
    config_class: type[DeviceConfig] = DeviceConfig

    def __init__(self, robot, *, run_dir: Path | None = None, session: Any = None, keys: Any = None, seed: int = 0,
                 device: Mapping[str, Any] | DeviceConfig | None = None,
                 site_datum: tuple[float, float, float] | None = None):
        self.robot = robot
        self.site_datum = site_datum  # the scenario's site.datum: where the site frame is on the globe (GNSS devices)
        self.robot_id = robot.id
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.session = session
        self.keys = keys
        self.seed = seed
        self.device_config = self._device_config(device if device is not None else getattr(robot, "device", None))
        self.ray_caster: Callable[[float, float, float], Any] | None = None
        """The world's lidar at an arbitrary pose of this robot, ``(x, y, yaw) -> ranges`` (its beam layout),
        for a device that scans at its own times; None: the device reuses the world's newest scan."""
        self._wall0 = time.monotonic()
        self._offset: float | None = None  # device time = offset + sim time, once in lock-step
        self.odom_sent = 0  # odometry samples sent, as the driver assembles them (the lock-step clock counts them)
        self.wire_received = 0  # messages from the driver handled (as its driver counts them: ``Driver.wire_sent``)
        self._status_due = 0.0  # monotonic time of the next status message while served (``serve``)

    def _device_config(self, settings) -> DeviceConfig:
        if isinstance(settings, self.config_class):
            return settings
        try:
            return self.config_class.from_settings(settings)
        except ValueError as e:
            raise DeviceError(f"robot {self.robot_id}: {self.kind} device: {e}") from None

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

    def host_clock(self, t_sim: float | None = None, offset_s: float = 0.0) -> float:
        """The device host's clock (what it stamps with): the world's clock (sim time in lock-step, the
        epoch in real time, as the world's own stamps) plus the host's ``offset_s`` (seconds ahead)."""
        base = t_sim if (self.in_lockstep and t_sim is not None) else time.time()
        return base + offset_s

    @property
    def in_lockstep(self) -> bool:
        return self._offset is not None

    def lockstep(self, t_sim: float) -> None:
        """From now on the world's sim time drives the device (stops the wall-clock thread); its device time is
        ``LOCKSTEP_EPOCH`` + sim time and its timers start again there."""
        self._stop_realtime()
        wall = self.wall_time()
        epoch = LOCKSTEP_EPOCH * math.ceil((wall + 1.0) / LOCKSTEP_EPOCH)  # LOCKSTEP_EPOCH unless up for 18 h
        self._offset = epoch - t_sim
        self._restart_timers(self.device_time(t_sim))

    def _restart_timers(self, t_dev: float) -> None:
        """Every timer of the device restarts at device time ``t_dev`` (the lock-step handover). Default: none."""

    # --- what the world calls -------------------------------------------------------------
    @abstractmethod
    def start(self) -> None:
        """Make the endpoint and run on the wall clock until ``lockstep``."""

    @abstractmethod
    def driver_params(self) -> dict[str, Any]:
        """Settings the agent's driver needs to find this device (e.g. ``{"channel": ...}``)."""

    def fleet_params(self) -> dict[str, Any]:
        """What the world tells the fleet to hand the agent's driver (``devices.json``): ``driver_params`` and
        whatever else the simulated site decides for it (a rover's datum)."""
        return self.driver_params()

    @abstractmethod
    def take_commands(self, t_sim: float) -> None:
        """Handle every message the driver has sent so far (they act from ``t_sim`` on)."""

    @abstractmethod
    def motion(self, t_sim_next: float) -> tuple[float, float]:
        """Advance the actuators to ``t_sim_next``; the body speeds (v [m/s], w [rad/s]) over the step."""

    @abstractmethod
    def report(self, t_sim_next: float, body: Body) -> None:
        """The body as the world moved it at ``t_sim_next``; send the telemetry due by then."""

    def serve(self, t_sim: float) -> None:
        """The world is not stepping (lock-step: waiting for agents to leave, or for a restarted one to open its
        driver) and stands at ``t_sim``: handle what came over the wire (replies go out at once) and, every
        ``SERVE_STATUS_S`` of wall time, the status a driver opening waits for (``_send_status``: heartbeats,
        odometry of the body standing where it is); no time passes for the device."""
        self.take_commands(t_sim)
        now = time.monotonic()
        if now >= self._status_due:
            self._status_due = now + SERVE_STATUS_S
            self._send_status(t_sim)

    def _send_status(self, t_sim: float) -> None:
        """What a driver opening waits for, sent while the world stands at ``t_sim`` (``serve``). Default: nothing."""

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


def device_class(driver: str) -> type[HostedDevice]:
    """The simulated device behind ``driver`` (its record in ``stack.drivers.DRIVERS``), imported now."""
    from ..drivers import DRIVERS

    rec = DRIVERS.get(driver)
    if rec is None or rec.device is None:
        raise DeviceError(f"no simulated device for driver {driver!r} (the world hosts {', '.join(hosted())})")
    return rec.device_class()


def hosted() -> list[str]:
    """The drivers the world hosts a simulated device for."""
    from ..drivers import DRIVERS

    return sorted(name for name, rec in DRIVERS.items() if rec.device)


def make_device(driver: str, robot, **kw) -> HostedDevice:
    return device_class(driver)(robot, **kw)


__all__ = ["LOCKSTEP_EPOCH", "Body", "DeviceConfig", "DeviceError", "HostedDevice", "check_choice", "check_number",
           "device_class", "hosted", "make_device"]
