"""Scenario files: the single place where YAML turns into typed configs.

Every field of ``shared/spec/INTERFACES.md`` section 2 is read here, checked for type and
range, and rejected with its path when unknown or wrong, e.g.::

    scenario.yaml: robots[2].pose: expected 3 numbers, got 2

The loader returns a frozen ``Scenario``; every process of a fleet (world, agents,
orchestrator) reads the same resolved file, written by the orchestrator next to the report.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from . import settings
from .models.geometry import slot_offset as _offset, slot_position  # eq. (3): the one copy
from .settings import kind as _kind

ROLES = ("leader", "follower")


def policy_names() -> tuple[str, ...]:
    """Every registered policy (``stack.policies.POLICIES``, out-of-tree ones included)."""
    from .policies import POLICIES

    return POLICIES.names()


def driver_names() -> tuple[str, ...]:
    """Every registered driver (``stack.drivers.DRIVERS``)."""
    from .drivers import DRIVERS

    return DRIVERS.names()


def __getattr__(name: str):  # POLICIES, DRIVERS: the registries' names, looked up when first asked for
    if name == "POLICIES":
        return policy_names()
    if name == "DRIVERS":
        return driver_names()
    raise AttributeError(name)


class ScenarioError(ValueError):
    """A scenario (or an override) that cannot be used. ``str()`` is the one-line message."""


# ---------------------------------------------------------------------------------------
# Typed configs
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Obstacle:
    """A static obstacle. ``type`` is cylinder, box or wall; unused fields stay 0."""

    type: str
    x: float = 0.0
    y: float = 0.0
    radius: float = 0.0
    size_x: float = 0.0
    size_y: float = 0.0
    yaw: float = 0.0  # rad
    start: tuple[float, float] = (0.0, 0.0)  # wall `from`
    end: tuple[float, float] = (0.0, 0.0)  # wall `to`
    thickness: float = 0.0
    virtual: bool = False
    """In a fleet with real robots: the obstacle is not in the real site, only in the world (the simulated robots
    see it; a real robot with ``lidar.virtual`` has it merged into its scan). False: it stands in the site too."""

    def as_box(self) -> tuple[float, float, float, float, float]:
        """Walls and boxes as (cx, cy, half_x, half_y, yaw)."""
        if self.type == "box":
            return self.x, self.y, self.size_x / 2, self.size_y / 2, self.yaw
        if self.type == "wall":
            (x0, y0), (x1, y1) = self.start, self.end
            length = math.hypot(x1 - x0, y1 - y0)
            return (x0 + x1) / 2, (y0 + y1) / 2, length / 2, self.thickness / 2, math.atan2(y1 - y0, x1 - x0)
        raise ValueError("a cylinder is not a box")


@dataclass(frozen=True)
class LidarConfig:
    """``robot.lidar``: the beams, field of view, range and noise of the scan, and where the scan comes from
    (``source``: the world, the base's driver, a ROS 2 topic, an RPLidar)."""

    beams: int = 180
    fov: float = math.pi  # rad (YAML: fov_deg)
    range: float = 5.0
    noise_std: float = 0.0
    source: str = "world"
    """Where the scans come from (``stack.drivers.LIDARS``): ``world``, ``ros2``, ``rplidar``."""
    mount: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The sensor's pose on the robot: x forward, y left [m], yaw [rad] (YAML: ``mount: [x, y, yaw_deg]``)."""
    blocks: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Each sensor source's settings (``robot.lidar.<source>``), as a dict of its config's fields."""
    device: dict[str, Any] = field(default_factory=dict)
    """Simulation only: the settings of the simulated lidar behind the source (``robot.lidar.device``)."""
    virtual: bool = False
    """A real robot (``embodiment: real``): merge the world's virtual robots and obstacles into its real scan
    (``stack.agents.virtual``); no effect on a simulated robot, whose scan is the world's already."""
    virtual_timeout: float = 0.5
    """[s] a virtual scan older than this (agent clock, from its arrival) is dropped from the merge."""
    virtual_lost_speed: float = 0.25
    """[m/s] while the virtual side is lost (after it was seen), forward speed is held to at most this."""

    @property
    def params(self) -> dict[str, Any]:
        """The chosen source's settings."""
        return dict(self.blocks.get(self.source, {}))


@dataclass(frozen=True)
class BaseConfig:
    """The differential-drive base behind the simulated driver."""

    track: float = 0.5  # wheel separation [m]
    wheel_radius: float = 0.1  # [m]
    wheel_accel: float = 30.0  # wheel angular acceleration limit [rad/s^2]


@dataclass(frozen=True)
class RobotConfig:
    """One robot: its ``robots[i]`` entry layered over the ``robot:`` defaults (pose, role, policy, driver,
    limits, lidar, noise, the policy's and the driver's own blocks, its embodiment)."""

    id: int
    role: str | None
    pose: tuple[float, float, float]  # x, y, yaw [rad]
    policy: str = "pid"
    driver: str = "sim"
    radius: float = 0.5
    v_max: float = 1.0
    w_max: float = 1.0
    lidar: LidarConfig = field(default_factory=LidarConfig)
    odom_noise: tuple[float, float] = (0.0, 0.0)  # v_std, w_std
    imu_noise: float = 0.0  # yaw-rate std [rad/s]
    fix: tuple[float, float] | None = None  # absolute position fixes (rate_hz, std [m]): GNSS / mocap stand-in
    comm_range: float = 10.0
    cmd_timeout: float = 0.5  # driver watchdog: stale command -> zero [s]
    base: BaseConfig = field(default_factory=BaseConfig)
    goal: tuple[float, float] | None = None
    driver_params: dict[str, dict[str, Any]] = field(default_factory=dict)  # driver name -> its settings
    device: dict[str, Any] = field(default_factory=dict)
    """Simulation only: the settings of the simulated device behind this robot's driver (``robot.device``:
    ``ideal`` for every device, then ``<driver>: {...}`` for the device behind that driver), resolved for
    its own driver; checked against that device's config (``stack/sim_bridge``'s ``DeviceConfig``s)."""
    odom_origin: str = "site"
    """Where the driver's odom frame lies in the site frame (``stack.agents.frames.OdomFrame``), resolved from
    ``robot.odom_origin`` (``auto`` | ``site`` | ``boot`` | ``boot-position`` | ``first``): ``site``, the odometry
    is in the site frame; ``boot``, it is (0, 0, 0) at the robot's ``pose`` (where it booted: a real Jackal, any
    hardware-like device); ``boot-position``, its origin is the start position but headings are the site's (an
    ArduPilot EKF origin set at boot); ``first``, the first sample is at ``pose``. ``auto`` (the default): ``site``
    where the simulated device is ideal (``robot.device.ideal``), else the device's own frame (``boot``; a
    ``mavlink`` rover ``boot-position``, or ``site`` with ``ekf_origin: site``; a ``jackal`` with
    ``odom_frame: site``, ``site``). The world's own ``sim`` base publishes its odometry in this frame."""
    guard: Any = None
    """``robot.guard`` resolved (``stack.agents.guard.GuardConfig``: margin, decel, lag_s, enabled): the collision
    guard under every policy; None where the scenario gives none (the defaults, on)."""
    stuck: Any = None
    """``robot.stuck`` resolved (``stack.agents.livelock.StuckConfig``: the stuck detector's window and tries, and its
    ``detour``, ``stack.agents.detour.DetourConfig``); None where the scenario gives none (the defaults, on)."""
    ros_graph: Any = None
    """``robot.ros_graph`` resolved (``stack.agents.ros_graph.RosGraphConfig``): the agent's estimate, slot and goal
    as ROS 2 topics (docs/ros2.md); None where the scenario gives none (off)."""
    settings: Mapping[str, Any] = field(default_factory=dict)
    """Policy settings key (``robot.<key>``) -> its resolved config dataclass: every block the scenario
    gives, and this robot's policy and ``pid`` (situation 1) with their defaults where it gives none."""
    embodiment: str = "simulated"
    """``simulated``: the world simulates the robot; ``real``: it lives outside the world (its agent runs where
    the robot is, on its own driver) and the world places a body at its pose (``pose_source``)."""
    pose_source: "PoseSource | None" = None
    """A real robot: where the world takes its pose from (None for a simulated robot)."""

    @property
    def policy_key(self) -> str:
        """The scenario block of this robot's policy's settings (``fuzzy`` for ``fuzzy-lstm``)."""
        from .policies import POLICIES

        return POLICIES[self.policy].settings_key

    def config_for(self, key: str):
        """The resolved config of the policy settings ``robot.<key>`` (its defaults where the scenario has none)."""
        if key in self.settings:
            return self.settings[key]
        from .policies import settings_class

        cls = settings_class(key)
        if cls is None:
            raise KeyError(f"no policy takes robot.{key} settings")
        return cls()

    def with_config(self, key: str, cfg) -> "RobotConfig":
        """This robot with ``cfg`` as its ``robot.<key>`` settings."""
        return replace(self, settings=dict(self.settings) | {key: cfg})

    def with_defaults(self, *keys: str) -> "RobotConfig":
        """This robot with the default config of each of ``keys`` it has no settings for (resolved, so logged); a
        policy that takes no settings (its record's ``config`` is None) has none to add."""
        from .policies import settings_class

        missing = {k: self.config_for(k) for k in keys if k not in self.settings and settings_class(k) is not None}
        return replace(self, settings=dict(self.settings) | missing) if missing else self


@dataclass(frozen=True)
class PoseSource:
    """Where the world takes a real robot's pose (``robots[i].pose_source``)."""

    key: str | None = None
    """A Zenoh key carrying ``geometry_msgs/msg/PoseStamped`` in CDR, in the site frame (a motion-capture system's
    topic through zenoh-bridge-ros2dds, e.g. ``vrpn_mocap/robot0/pose``); None: the robot's own published estimate
    (its ``state``)."""
    stale_after_s: float = 0.5
    """[s] a pose older than this (world clock, from its arrival) is stale: the body stays at its last pose, grown
    by the distance the robot could have driven since (at ``v_max``, at most ``STALE_GROWTH_MAX_M``)."""


@dataclass(frozen=True)
class BurstConfig:
    """Gilbert-Elliott two-state channel."""

    p_good_bad: float
    p_bad_good: float
    loss_bad: float
    loss_good: float = 0.0


@dataclass(frozen=True)
class CommConfig:
    """``comm``: the radio model applied at each receiver: loss, burst loss (Gilbert-Elliott) and latency."""

    loss: float = 0.0
    burst: BurstConfig | None = None
    latency_ms: float = 0.0
    jitter_ms: float = 0.0


@dataclass(frozen=True)
class Slot:
    L: float
    psi: float  # rad


@dataclass(frozen=True)
class SlotChange:
    """``formation.schedule[i]``: from sim time ``at`` on, these followers take these slots."""

    at: float
    slots: dict[int, Slot]


@dataclass(frozen=True)
class FormationConfig:
    """``formation``: the leader, the goal and each follower's slot (``L``, ``psi_deg`` behind the leader),
    with slot changes over time."""

    leader: int
    goal: tuple[float, float]
    slots: dict[int, Slot]  # the slots at t = 0
    d_safe: float = 3.0  # Bai 2022 section V-A
    d_leader_slow: float = 5.0  # eq. (20)
    schedule: tuple[SlotChange, ...] = ()  # formation changes in time (Deng section 5.1), sorted by ``at``

    def slots_at(self, t: float) -> dict[int, Slot]:
        """The slots in force at sim time ``t``: each change overrides the followers it names."""
        out = dict(self.slots)
        for ch in self.schedule:
            if ch.at > t + 1e-9:
                break
            out.update(ch.slots)
        return out

    @property
    def final_slots(self) -> dict[int, Slot]:
        return self.slots_at(math.inf)

    def resolve(self, t: float, dead: set[int] | frozenset[int] = frozenset()) -> tuple[int | None, dict[int, Slot]]:
        """(leader, slots) at sim time ``t`` once the robots in ``dead`` are gone.

        Failover rule, the same in every agent, the world and the report: while the leader
        lives nothing changes but the dead followers' slots; when it is gone the live robot
        with the lowest id leads, and every other follower keeps its place in the shape:
        its new slot is its old slot minus the new leader's old slot (eq. (3) offsets, so the
        formation keeps its geometry around the robot that now leads). (None, {}) if nobody
        is left.
        """
        slots = self.slots_at(t)
        if self.leader not in dead:
            return self.leader, {r: s for r, s in slots.items() if r not in dead}
        live = sorted(r for r in slots if r not in dead)
        if not live:
            return None, {}
        new = live[0]
        ox, oy = _offset(slots[new])
        out = {}
        for r in live[1:]:
            x, y = _offset(slots[r])
            dx, dy = x - ox, y - oy
            out[r] = Slot(L=math.hypot(dx, dy), psi=math.atan2(dy, dx))
        return new, out


@dataclass(frozen=True)
class SuccessConfig:
    """``success``: what a run must meet: the leader within ``goal_tolerance`` of the goal before ``max_time``,
    and no collision if ``no_collisions``."""

    goal_tolerance: float = 0.5
    max_time: float | None = None
    no_collisions: bool = True
    settle_s: float = 10.0
    """[s] (beyond the contract) after the leader arrives, a run that stops early goes on at most this long for
    the followers to settle in their slots; 0 ends it when the leader arrives."""


@dataclass(frozen=True)
class BenchConfig:
    """What ``stack-fleet bench`` does with this scenario (an addition to the contract's format)."""

    policies: tuple[str, ...] = field(default_factory=policy_names)  # the policies this scenario is meant for
    reference: str = ""  # the paper's figure this scenario reproduces, as text for the table


@dataclass(frozen=True)
class SiteConfig:
    """``site:`` (optional, top level): where the site frame is on the globe."""

    datum: tuple[float, float, float] | None = None
    """(lat [deg], lon [deg], alt [m]) of the site frame's origin on WGS84 (x east, y north); GNSS-based
    drivers (MAVLink) place the robot relative to it. None: the site is not tied to the globe."""


@dataclass(frozen=True)
class Scenario:
    """A whole scenario file, parsed and checked (``parse_scenario``, ``load_scenario``): the world,
    the robots (each a ``RobotConfig`` over the ``robot:`` defaults), the formation, the radio model, the
    success criteria and the bench settings. Unknown keys are errors."""

    name: str
    seed: int
    dt: float
    duration: float
    obstacles: tuple[Obstacle, ...]
    robots: tuple[RobotConfig, ...]
    comm: CommConfig
    formation: FormationConfig | None
    coordination: str | None
    success: SuccessConfig
    bench: BenchConfig = field(default_factory=BenchConfig)
    site: "SiteConfig" = field(default_factory=lambda: SiteConfig())
    source: str = "<scenario>"
    raw: dict = field(default_factory=dict, compare=False, repr=False)

    def robot(self, robot_id: int) -> RobotConfig:
        for r in self.robots:
            if r.id == robot_id:
                return r
        raise ScenarioError(f"{self.source}: robots: no robot with id {robot_id}")

    @property
    def ids(self) -> list[int]:
        return [r.id for r in self.robots]

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.raw, sort_keys=False)


# ---------------------------------------------------------------------------------------
# Field checks
# ---------------------------------------------------------------------------------------


class _Reader:
    def __init__(self, source: str):
        self.source = source

    def fail(self, path: str, what: str) -> ScenarioError:
        return ScenarioError(f"{self.source}: {path}: {what}")

    def mapping(self, value: Any, path: str, allowed: set[str]) -> dict:
        if not isinstance(value, dict):
            raise self.fail(path, f"expected a mapping, got {_kind(value)}")
        for key in value:
            if key not in allowed:
                raise self.fail(f"{path}.{key}" if path else str(key), f"unknown field (allowed: {', '.join(sorted(allowed)) or 'none'})")
        return value

    def number(self, value: Any, path: str, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(path, f"expected a number, got {_kind(value)}")
        v = float(value)
        if not math.isfinite(v):
            raise self.fail(path, f"expected a finite number, got {value}")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise self.fail(path, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
        if hi is not None and v > hi:
            raise self.fail(path, f"must be <= {hi:g}, got {v:g}")
        return v

    def integer(self, value: Any, path: str, lo: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(path, f"expected an integer, got {_kind(value)}")
        if lo is not None and value < lo:
            raise self.fail(path, f"must be >= {lo}, got {value}")
        return value

    def vector(self, value: Any, path: str, n: int) -> tuple[float, ...]:
        if not isinstance(value, (list, tuple)):
            raise self.fail(path, f"expected {n} numbers, got {_kind(value)}")
        if len(value) != n:
            raise self.fail(path, f"expected {n} numbers, got {len(value)}")
        return tuple(self.number(v, f"{path}[{i}]") for i, v in enumerate(value))

    def choice(self, value: Any, path: str, options: tuple[str, ...]) -> str:
        if value not in options:
            raise self.fail(path, f"expected one of {', '.join(options)}, got {value!r}")
        return value

    def boolean(self, value: Any, path: str) -> bool:
        if not isinstance(value, bool):
            raise self.fail(path, f"expected true or false, got {_kind(value)}")
        return value


def _max(rd: "_Reader", v: int, hi: int, path: str) -> int:
    if v > hi:
        raise rd.fail(path, f"must be <= {hi}, got {v}")
    return v


_CORE_KEYS = {"radius", "v_max", "w_max", "lidar", "odom_noise", "imu_noise", "fix", "comm_range", "cmd_timeout", "base",
              "policy", "driver", "device", "odom_origin", "ros_graph", "guard", "stuck"}

ODOM_ORIGINS = ("auto", "site", "boot", "boot-position", "first")


def _robot_keys() -> set[str]:
    """What ``robot:`` and ``robots[i]`` may hold: the core fields, every policy's settings block, every driver's."""
    from .drivers import DRIVERS
    from .policies import POLICIES

    return _CORE_KEYS | {p.settings_key for p in POLICIES.values()} | set(DRIVERS)


def _robot_fields(rd: _Reader, d: dict, path: str, base: dict[str, Any]) -> dict[str, Any]:
    """Read the per-robot fields shared by ``robot:`` (defaults) and ``robots[i]``, over ``base``."""
    out = dict(base)
    _limits(rd, d, path, out)
    _sensor_noise(rd, d, path, out)
    if "lidar" in d:
        out["lidar"] = _lidar(rd, d["lidar"], f"{path}.lidar", out.get("lidar", LidarConfig()))
    if "base" in d:
        out["base"] = _base(rd, d["base"], f"{path}.base", out.get("base", BaseConfig()))
    if "policy" in d:
        out["policy"] = rd.choice(d["policy"], f"{path}.policy", policy_names())
    if "driver" in d:
        out["driver"] = rd.choice(d["driver"], f"{path}.driver", driver_names())
    out["settings"] = _policy_blocks(rd, d, path, out.get("settings", {}))
    out["driver_params"] = _driver_blocks(rd, d, path, out.get("driver_params", {}))
    if "device" in d:
        out["device_blocks"] = _device_blocks(rd, d["device"], f"{path}.device", out.get("device_blocks", {}))
    if "odom_origin" in d:
        out["odom_origin"] = rd.choice(d["odom_origin"], f"{path}.odom_origin", ODOM_ORIGINS)
    if "ros_graph" in d:
        out["ros_graph"] = _ros_graph(rd, d["ros_graph"], f"{path}.ros_graph", out.get("ros_graph"))
    if "guard" in d:
        out["guard"] = _safety(rd, "guard", d["guard"], f"{path}.guard", out.get("guard"))
    if "stuck" in d:
        out["stuck"] = _safety(rd, "stuck", d["stuck"], f"{path}.stuck", out.get("stuck"))
    return out


def _safety(rd: _Reader, key: str, value: Any, path: str, prev):
    """``robot.guard`` (``stack.agents.guard.GuardConfig``) or ``robot.stuck`` (``stack.agents.livelock.StuckConfig``)
    over the defaults' (``prev``)."""
    if key == "guard":
        from .agents.guard import GuardConfig as cls
    else:
        from .agents.livelock import StuckConfig as cls

    try:
        return settings.read(cls, value, path, prev)
    except settings.SettingError as e:
        raise rd.fail(e.path, e.what) from None


def _ros_graph(rd: _Reader, value: Any, path: str, prev):
    """``robot.ros_graph`` over the defaults' (``prev``); imported only when a scenario has one."""
    from .agents.ros_graph import RosGraphConfig

    try:
        return settings.read(RosGraphConfig, value, path, prev)
    except settings.SettingError as e:
        raise rd.fail(e.path, e.what) from None


def _device_blocks(rd: _Reader, value: Any, path: str, base: Mapping[str, Any]) -> dict[str, Any]:
    """``device: {ideal: bool, <driver>: {...}}`` over the defaults' (``base``); each driver's block is
    checked when a robot with that driver resolves it (``_resolve_device``)."""
    from .drivers import DRIVERS

    m = rd.mapping(value or {}, path, {"ideal"} | {n for n, rec in DRIVERS.items() if rec.device})
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for key, v in m.items():
        if key == "ideal":
            out["ideal"] = rd.boolean(v, f"{path}.ideal")
        else:
            out[key] = dict(out.get(key, {})) | dict(rd.mapping(v or {}, f"{path}.{key}", _device_keys(key)))
    return out


def _device_keys(driver: str) -> set[str]:
    """The settings of the simulated device behind ``driver`` (simulation only: imported when a block names it)."""
    import dataclasses

    from .sim_bridge.devices import device_class

    return {f.name for f in dataclasses.fields(device_class(driver).config_class)}


def _resolve_device(rd: _Reader, blocks: Mapping[str, Any], driver: str, path: str) -> dict[str, Any]:
    """The robot's own device settings: ``ideal`` then its driver's block, checked by the device's config."""
    out = {"ideal": blocks["ideal"]} if "ideal" in blocks else {}
    out |= dict(blocks.get(driver, {}))
    if out and driver in _hosted():
        from .sim_bridge.devices import device_class

        try:
            device_class(driver).config_class.from_settings(out)
        except ValueError as e:
            raise rd.fail(f"{path}.device.{driver}" if driver in blocks else f"{path}.device", str(e)) from None
    return out if driver in _hosted() else {}


def _odom_origin(chosen: str, blocks: Mapping[str, Any], driver: str) -> str:
    """``robot.odom_origin`` resolved for a robot with ``driver`` and its device ``blocks`` (see RobotConfig)."""
    if chosen != "auto":
        return chosen
    if driver in _hosted():
        from .sim_bridge.devices import DeviceConfig  # stdlib only: no simulator imported

        ideal = blocks.get("ideal", DeviceConfig().ideal)
    else:
        ideal = blocks.get("ideal", True)  # the world's own base, or a robot no simulator stands in for
    own = dict(blocks.get(driver, {}))
    if ideal or own.get("ekf_origin") == "site" or own.get("odom_frame") == "site":
        return "site"
    return "boot-position" if driver == "mavlink" else "boot"


def _hosted() -> set[str]:
    from .drivers import DRIVERS

    return {n for n, rec in DRIVERS.items() if rec.device}


def _limits(rd: _Reader, d: dict, path: str, out: dict[str, Any]) -> None:
    """Size, speed limits, comm range and the command watchdog."""
    for key, hi in (("radius", 10.0), ("v_max", 20.0), ("w_max", 20.0), ("comm_range", None), ("cmd_timeout", 10.0)):
        if key in d:
            out[key] = rd.number(d[key], f"{path}.{key}", 0.0, hi, lo_open=True)


def _sensor_noise(rd: _Reader, d: dict, path: str, out: dict[str, Any]) -> None:
    """``imu_noise``, ``odom_noise`` and the simulated position ``fix``."""
    if "imu_noise" in d:
        m = rd.mapping(d["imu_noise"], f"{path}.imu_noise", {"w_std"})
        out["imu_noise"] = rd.number(m.get("w_std", 0.0), f"{path}.imu_noise.w_std", 0.0)
    if "fix" in d:
        out["fix"] = None if d["fix"] is None else _fix(rd, d["fix"], f"{path}.fix")
    if "odom_noise" in d:
        m = rd.mapping(d["odom_noise"], f"{path}.odom_noise", {"v_std", "w_std"})
        prev = out.get("odom_noise", (0.0, 0.0))
        out["odom_noise"] = (
            rd.number(m.get("v_std", prev[0]), f"{path}.odom_noise.v_std", 0.0),
            rd.number(m.get("w_std", prev[1]), f"{path}.odom_noise.w_std", 0.0),
        )


def _fix(rd: _Reader, value: Any, path: str) -> tuple[float, float]:
    m = rd.mapping(value, path, {"rate_hz", "std"})
    for k in ("rate_hz", "std"):
        if k not in m:
            raise rd.fail(f"{path}.{k}", "missing")
    return (rd.number(m["rate_hz"], f"{path}.rate_hz", 0.0, 1000.0, lo_open=True),
            rd.number(m["std"], f"{path}.std", 0.0, 100.0, lo_open=True))


def _lidar(rd: _Reader, value: Any, path: str, prev: LidarConfig) -> LidarConfig:
    from .drivers import LIDARS

    sources = {n for n, rec in LIDARS.items() if rec.config}
    m = rd.mapping(value, path, {"beams", "fov_deg", "range", "noise_std", "source", "mount", "device", "virtual",
                                 "virtual_timeout", "virtual_lost_speed"} | sources)
    mount = prev.mount
    if "mount" in m:
        mx, my, myaw = rd.vector(m["mount"], f"{path}.mount", 3)
        mount = (mx, my, math.radians(myaw))
    out = LidarConfig(
        beams=_max(rd, rd.integer(m.get("beams", prev.beams), f"{path}.beams", 1), 10_000, f"{path}.beams"),
        fov=math.radians(rd.number(m.get("fov_deg", math.degrees(prev.fov)), f"{path}.fov_deg", 0.0, 360.0, lo_open=True)),
        range=rd.number(m.get("range", prev.range), f"{path}.range", 0.0, 100.0, lo_open=True),
        noise_std=rd.number(m.get("noise_std", prev.noise_std), f"{path}.noise_std", 0.0),
        source=rd.choice(m.get("source", prev.source), f"{path}.source", LIDARS.names()), mount=mount,
        blocks=_lidar_blocks(rd, m, path, prev.blocks, sources),
        device=dict(prev.device) | dict(rd.mapping(m.get("device") or {}, f"{path}.device", _lidar_device_keys(m, prev))),
        virtual=rd.boolean(m.get("virtual", prev.virtual), f"{path}.virtual"),
        virtual_timeout=rd.number(m.get("virtual_timeout", prev.virtual_timeout), f"{path}.virtual_timeout", 0.0, 60.0,
                                  lo_open=True),
        virtual_lost_speed=rd.number(m.get("virtual_lost_speed", prev.virtual_lost_speed), f"{path}.virtual_lost_speed",
                                     0.0, 20.0),
    )
    _check_lidar_device(rd, out, path)
    return out


def _lidar_blocks(rd: _Reader, m: dict, path: str, base: Mapping[str, dict], sources: set[str]) -> dict[str, dict]:
    """``robot.lidar.<source>`` of every sensor source: its config's fields, each block over the defaults'."""
    from .drivers import LIDARS

    out = dict(base)
    for name in sorted(sources & set(m)):
        p, cls = f"{path}.{name}", LIDARS[name].config_class()
        merged = dict(out.get(name, {})) | dict(rd.mapping(m[name] or {}, p, settings.keys(cls)))
        try:
            cfg = settings.read(cls, merged, p)
        except settings.SettingError as e:
            raise rd.fail(e.path, e.what) from None
        out[name] = {k: getattr(cfg, k) for k in merged}
    return out


def _lidar_device_keys(m: dict, prev: LidarConfig) -> set[str]:
    """The simulated lidar's settings for the source ``m`` (or ``prev``) names; none for ``world``."""
    import dataclasses

    source = m.get("source", prev.source)
    if source == "world" or "device" not in m:
        return set()
    from .sim_bridge.lidar_devices import lidar_device_class

    return {f.name for f in dataclasses.fields(lidar_device_class(source).config_class)}


def _check_lidar_device(rd: _Reader, lid: LidarConfig, path: str) -> None:
    if lid.source == "world" or not lid.device:
        return
    from .sim_bridge.lidar_devices import lidar_device_class

    try:
        lidar_device_class(lid.source).config_class.from_settings(lid.device)
    except ValueError as e:
        raise rd.fail(f"{path}.device", str(e)) from None


def _base(rd: _Reader, value: Any, path: str, prev: BaseConfig) -> BaseConfig:
    m = rd.mapping(value, path, {"track", "wheel_radius", "wheel_accel"})
    return BaseConfig(
        track=rd.number(m.get("track", prev.track), f"{path}.track", 0.0, 10.0, lo_open=True),
        wheel_radius=rd.number(m.get("wheel_radius", prev.wheel_radius), f"{path}.wheel_radius", 0.0, 5.0, lo_open=True),
        wheel_accel=rd.number(m.get("wheel_accel", prev.wheel_accel), f"{path}.wheel_accel", 0.0, lo_open=True),
    )


def _policy_blocks(rd: _Reader, d: dict, path: str, base: Mapping[str, Any]) -> dict[str, Any]:
    """``robot.<key>`` of every policy: its config dataclass, each block over the defaults' (``base``)."""
    from .policies import POLICIES

    out = dict(base)
    for key in dict.fromkeys(p.settings_key for p in POLICIES.values()):
        if key in d:
            try:
                out[key] = settings.read(POLICIES.by_key(key).config_class(), d[key], f"{path}.{key}", out.get(key))
            except settings.SettingError as e:
                raise rd.fail(e.path, e.what) from None
    return out


def _driver_blocks(rd: _Reader, d: dict, path: str, base: Mapping[str, dict]) -> dict[str, dict[str, Any]]:
    """``robot.<driver>`` of every driver: a dict of its config dataclass's fields (each block over the
    defaults'), checked by building that dataclass; the driver builds its own from it (``Driver._configure``)."""
    from .drivers import DRIVERS

    out = dict(base)
    for name, rec in DRIVERS.items():
        if name not in d:
            continue
        p = f"{path}.{name}"
        allowed = settings.keys(rec.config_class()) if rec.config else set()
        merged = dict(out.get(name, {})) | dict(rd.mapping(d[name] or {}, p, allowed))
        if merged:
            try:
                cfg = settings.read(rec.config_class(), merged, p)
            except settings.SettingError as e:
                raise rd.fail(e.path, e.what) from None
            merged = {k: getattr(cfg, k) for k in merged}
        out[name] = merged
    return out


def _slots(rd: _Reader, slots_d: Any, path: str, seen: set[int], leader: int) -> dict[int, Slot]:
    """A mapping of follower id -> {L, psi_deg} (``formation.slots`` and each schedule entry's)."""
    if not isinstance(slots_d, dict):
        raise rd.fail(path, f"expected a mapping of robot id to {{L, psi_deg}}, got {_kind(slots_d)}")
    slots: dict[int, Slot] = {}
    for key, s in slots_d.items():
        sp = f"{path}.{key}"
        if isinstance(key, bool) or not (isinstance(key, int) or (isinstance(key, str) and key.isascii() and key.isdigit())):
            raise rd.fail(sp, "slot keys are robot ids")
        sid = int(key)
        if sid not in seen:
            raise rd.fail(sp, f"no robot with id {sid}")
        if sid == leader:
            raise rd.fail(sp, "the leader has no slot")
        s = rd.mapping(s, sp, {"L", "psi_deg"})
        for k in ("L", "psi_deg"):
            if k not in s:
                raise rd.fail(f"{sp}.{k}", "missing")
        slots[sid] = Slot(L=rd.number(s["L"], f"{sp}.L", 0.0), psi=math.radians(rd.number(s["psi_deg"], f"{sp}.psi_deg")))
    return slots


def _obstacle(rd: _Reader, d: Any, path: str) -> Obstacle:
    if not isinstance(d, dict) or "type" not in d:
        raise rd.fail(path, "expected a mapping with a type (cylinder, box or wall)")
    if "virtual" in d:  # in the world only, not in the real site
        virtual = rd.boolean(d["virtual"], f"{path}.virtual")
        return replace(_obstacle(rd, {k: v for k, v in d.items() if k != "virtual"}, path), virtual=virtual)
    kind = rd.choice(d["type"], f"{path}.type", ("cylinder", "box", "wall"))
    if kind == "cylinder":
        rd.mapping(d, path, {"type", "x", "y", "radius"})
        for k in ("x", "y", "radius"):
            if k not in d:
                raise rd.fail(f"{path}.{k}", "missing")
        return Obstacle("cylinder", x=rd.number(d["x"], f"{path}.x"), y=rd.number(d["y"], f"{path}.y"),
                        radius=rd.number(d["radius"], f"{path}.radius", 0.0, lo_open=True))
    if kind == "box":
        rd.mapping(d, path, {"type", "x", "y", "size_x", "size_y", "yaw_deg"})
        for k in ("x", "y", "size_x", "size_y"):
            if k not in d:
                raise rd.fail(f"{path}.{k}", "missing")
        return Obstacle("box", x=rd.number(d["x"], f"{path}.x"), y=rd.number(d["y"], f"{path}.y"),
                        size_x=rd.number(d["size_x"], f"{path}.size_x", 0.0, lo_open=True),
                        size_y=rd.number(d["size_y"], f"{path}.size_y", 0.0, lo_open=True),
                        yaw=math.radians(rd.number(d.get("yaw_deg", 0.0), f"{path}.yaw_deg")))
    rd.mapping(d, path, {"type", "from", "to", "thickness"})
    for k in ("from", "to"):
        if k not in d:
            raise rd.fail(f"{path}.{k}", "missing")
    a = rd.vector(d["from"], f"{path}.from", 2)
    b = rd.vector(d["to"], f"{path}.to", 2)
    if a == b:
        raise rd.fail(f"{path}.to", "a wall needs two different end points")
    return Obstacle("wall", start=a, end=b, thickness=rd.number(d.get("thickness", 0.2), f"{path}.thickness", 0.0, lo_open=True))


_TOP_KEYS = {"name", "seed", "dt", "duration", "world", "robot", "comm", "formation", "robots", "success", "coordination",
             "bench", "site"}


def parse_scenario(data: Any, source: str = "<scenario>") -> Scenario:
    """Validate a scenario given as parsed YAML; raise ``ScenarioError`` on the first problem."""
    rd = _Reader(source)
    d = rd.mapping(data, "", _TOP_KEYS)
    for k in ("dt", "robots"):
        if k not in d:
            raise rd.fail(k, "missing")
    seed = rd.integer(d.get("seed", 0), "seed", 0)
    dt = rd.number(d["dt"], "dt", 0.0, 10.0, lo_open=True)
    duration = rd.number(d.get("duration", 120.0), "duration", 0.0, lo_open=True)
    if duration < dt:
        raise rd.fail("duration", f"must be at least one step (dt = {dt:g}), got {duration:g}")
    obstacles = _world(rd, d.get("world", {}) or {})
    defaults = _robot_fields(rd, rd.mapping(d.get("robot", {}) or {}, "robot", _robot_keys()), "robot", {})
    comm = _comm(rd, d.get("comm", {}) or {})
    coordination = rd.choice(d["coordination"], "coordination", ("arrival_time",)) if "coordination" in d else None
    robots = _robots(rd, d["robots"], defaults)
    formation = None
    if d.get("formation") is not None:
        formation = _formation(rd, d["formation"], {r.id for r in robots}, duration)
        robots = _formation_roles(rd, formation, robots)
    elif coordination == "arrival_time":
        _arrival_peers(rd, robots)
    else:
        raise rd.fail("formation", "missing (or give every robot a goal and coordination: arrival_time)")
    return Scenario(name=str(d.get("name", Path(source).stem)), seed=seed, dt=dt, duration=duration, obstacles=obstacles,
                    robots=tuple(robots), comm=comm, formation=formation, coordination=coordination,
                    success=_success(rd, d.get("success", {}) or {}), bench=_bench(rd, d.get("bench")),
                    site=_site(rd, d.get("site")), source=source, raw=data)


def _site(rd: _Reader, value: Any) -> SiteConfig:
    if value is None:
        return SiteConfig()
    m = rd.mapping(value, "site", {"datum"})
    if m.get("datum") is None:
        return SiteConfig()
    lat, lon, alt = rd.vector(m["datum"], "site.datum", 3)
    rd.number(lat, "site.datum[0]", -89.0, 89.0)  # the tangent plane is no use at the poles
    rd.number(lon, "site.datum[1]", -180.0, 180.0)
    rd.number(alt, "site.datum[2]", -1000.0, 10_000.0)
    return SiteConfig(datum=(lat, lon, alt))


def _world(rd: _Reader, value: Any) -> tuple[Obstacle, ...]:
    world = rd.mapping(value, "world", {"obstacles"})
    obs_list = world.get("obstacles", []) or []
    if not isinstance(obs_list, list):
        raise rd.fail("world.obstacles", f"expected a list, got {_kind(obs_list)}")
    return tuple(_obstacle(rd, o, f"world.obstacles[{i}]") for i, o in enumerate(obs_list))


def _comm(rd: _Reader, value: Any) -> CommConfig:
    comm_d = rd.mapping(value, "comm", {"loss", "burst", "latency_ms", "jitter_ms"})
    burst = None
    if comm_d.get("burst") is not None:
        b = rd.mapping(comm_d["burst"], "comm.burst", {"p_good_bad", "p_bad_good", "loss_bad", "loss_good"})
        for k in ("p_good_bad", "p_bad_good", "loss_bad"):
            if k not in b:
                raise rd.fail(f"comm.burst.{k}", "missing")
        burst = BurstConfig(**{k: rd.number(v, f"comm.burst.{k}", 0.0, 1.0) for k, v in b.items()})
        if burst.p_bad_good == 0.0:
            raise rd.fail("comm.burst.p_bad_good", "must be > 0, or the channel never leaves the bad state")
    return CommConfig(
        loss=rd.number(comm_d.get("loss", 0.0), "comm.loss", 0.0, 1.0),
        burst=burst,
        latency_ms=rd.number(comm_d.get("latency_ms", 0.0), "comm.latency_ms", 0.0, 60_000.0),
        jitter_ms=rd.number(comm_d.get("jitter_ms", 0.0), "comm.jitter_ms", 0.0, 60_000.0),
    )


def _robots(rd: _Reader, robots_d: Any, defaults: dict[str, Any]) -> list[RobotConfig]:
    if not isinstance(robots_d, list) or not robots_d:
        raise rd.fail("robots", f"expected a non-empty list, got {_kind(robots_d)}")
    robots: list[RobotConfig] = []
    seen: set[int] = set()
    for i, r in enumerate(robots_d):
        robot = _robot(rd, r, f"robots[{i}]", defaults)
        if robot.id in seen:
            raise rd.fail(f"robots[{i}].id", f"duplicate id {robot.id}")
        seen.add(robot.id)
        robots.append(robot)
    return robots


def _robot(rd: _Reader, r: Any, p: str, defaults: dict[str, Any]) -> RobotConfig:
    """One ``robots[i]``: id, pose, role and goal, then its own fields over the ``robot:`` defaults."""
    r = rd.mapping(r, p, _robot_keys() | _ENTRY_KEYS)
    for k in ("id", "pose"):
        if k not in r:
            raise rd.fail(f"{p}.{k}", "missing")
    rid = _max(rd, rd.integer(r["id"], f"{p}.id", 0), 65535, f"{p}.id")
    x, y, yaw_deg = rd.vector(r["pose"], f"{p}.pose", 3)
    role = rd.choice(r["role"], f"{p}.role", ROLES) if "role" in r else None
    goal = rd.vector(r["goal"], f"{p}.goal", 2) if "goal" in r else None
    fields_ = _robot_fields(rd, r, p, defaults)
    blocks, driver = fields_.pop("device_blocks", {}), fields_.get("driver", "sim")
    fields_["device"] = _resolve_device(rd, blocks, driver, p)
    fields_["odom_origin"] = _odom_origin(fields_.get("odom_origin", "auto"), blocks, driver)
    fields_["embodiment"] = rd.choice(r.get("embodiment", "simulated"), f"{p}.embodiment", EMBODIMENTS)
    fields_["pose_source"] = _pose_source(rd, r, p, fields_)
    robot = RobotConfig(id=rid, role=role, pose=(x, y, math.radians(yaw_deg)), goal=goal, **fields_)
    return robot.with_defaults("pid", robot.policy_key)


EMBODIMENTS = ("simulated", "real")
_ENTRY_KEYS = {"id", "role", "pose", "goal", "embodiment", "pose_source"}
SIMULATION_ONLY = ("device", "odom_noise", "imu_noise", "base", "fix")
"""What a ``robots[i]`` entry of a real robot may not set: settings of the world's simulated base and sensors."""


def _pose_source(rd: _Reader, r: dict, p: str, fields_: dict[str, Any]) -> PoseSource | None:
    """A real robot's ``pose_source`` (its estimate by default), after the checks a real robot's entry must pass."""
    if fields_["embodiment"] == "simulated":
        if "pose_source" in r:
            raise rd.fail(f"{p}.pose_source", "only a real robot (embodiment: real) has a pose source")
        return None
    for k in SIMULATION_ONLY:
        if k in r:
            raise rd.fail(f"{p}.{k}", "a real robot has no simulated base or sensors (simulation only)")
    if isinstance(r.get("lidar"), dict) and "device" in r["lidar"]:
        raise rd.fail(f"{p}.lidar.device", "a real robot has no simulated lidar (simulation only)")
    driver = fields_.get("driver", "sim")
    if driver == "sim":
        raise rd.fail(f"{p}.driver", "a real robot needs the driver of its base (jackal, can, mavlink); "
                                     "sim is the world's simulated base")
    if fields_.get("lidar", LidarConfig()).source == "world" and not _reads_scan(driver):
        raise rd.fail(f"{p}.lidar.source", f"the world does not scan for a real robot: name its lidar (ros2, rplidar) "
                                           f"or use a driver that reads one ({driver} does not)")
    m = rd.mapping(r.get("pose_source") or {}, f"{p}.pose_source", {"key", "stale_after_s"})
    key = m.get("key")
    if key is not None:
        from .comm.keys import check_key_expr

        if not isinstance(key, str) or not key or (why := check_key_expr(key)) is not None:
            raise rd.fail(f"{p}.pose_source.key", f"not a Zenoh key: {key!r}" + (f" ({why})" if isinstance(key, str) and key else ""))
    stale = rd.number(m.get("stale_after_s", 0.5), f"{p}.pose_source.stale_after_s", 0.0, 60.0, lo_open=True)
    return PoseSource(key=key, stale_after_s=stale)


def _reads_scan(driver: str) -> bool:
    from .drivers import DRIVERS

    return bool(getattr(DRIVERS[driver].make(), "provides_scan", False))


class _FileReader(_Reader):
    """Paths from a file's root (a robot's own file: ``can.channel``, not ``robots[2].can.channel``)."""

    def fail(self, path: str, what: str) -> ScenarioError:
        return super().fail(path.lstrip(".") or "(top level)", what)


def check_robot_entry(data: Any, source: str) -> None:
    """A robot's own settings file (``stack.robotfile``): the keys of one ``robots[i]`` entry, none of them
    required, each checked as the scenario checks it; errors name ``source`` and the key's path in it."""
    rd = _FileReader(source)
    d = rd.mapping(data, "", _robot_keys() | _ENTRY_KEYS)
    if "embodiment" in d:
        rd.choice(d["embodiment"], "embodiment", EMBODIMENTS)
    if "id" in d:
        _max(rd, rd.integer(d["id"], "id", 0), 65535, "id")
    if "pose" in d:
        rd.vector(d["pose"], "pose", 3)
    if "role" in d:
        rd.choice(d["role"], "role", ROLES)
    if "goal" in d:
        rd.vector(d["goal"], "goal", 2)
    fields_ = _robot_fields(rd, d, "", {})
    if "driver" in d:  # its device block, where the same file says which driver it is for
        _resolve_device(rd, fields_.get("device_blocks", {}), fields_["driver"], "")


def _formation(rd: _Reader, value: Any, seen: set[int], duration: float) -> FormationConfig:
    f = rd.mapping(value, "formation", {"leader", "goal", "slots", "d_safe", "schedule"})
    for k in ("leader", "goal"):
        if k not in f:
            raise rd.fail(f"formation.{k}", "missing")
    leader = rd.integer(f["leader"], "formation.leader", 0)
    if leader not in seen:
        raise rd.fail("formation.leader", f"no robot with id {leader}")
    return FormationConfig(
        leader=leader,
        goal=rd.vector(f["goal"], "formation.goal", 2),
        slots=_slots(rd, f.get("slots", {}) or {}, "formation.slots", seen, leader),
        d_safe=rd.number(f.get("d_safe", 3.0), "formation.d_safe", 0.0),
        schedule=_schedule(rd, f.get("schedule") or [], seen, leader, duration),
    )


def _schedule(rd: _Reader, sched: Any, seen: set[int], leader: int, duration: float) -> tuple[SlotChange, ...]:
    if not isinstance(sched, list):
        raise rd.fail("formation.schedule", f"expected a list of {{at, slots}}, got {_kind(sched)}")
    schedule: list[SlotChange] = []
    for i, e in enumerate(sched):
        ep = f"formation.schedule[{i}]"
        e = rd.mapping(e, ep, {"at", "slots"})
        for k in ("at", "slots"):
            if k not in e:
                raise rd.fail(f"{ep}.{k}", "missing")
        at = rd.number(e["at"], f"{ep}.at", 0.0, duration)
        if schedule and at <= schedule[-1].at:
            raise rd.fail(f"{ep}.at", f"must be later than the previous change ({schedule[-1].at:g} s), got {at:g}")
        ch = _slots(rd, e["slots"], f"{ep}.slots", seen, leader)
        if not ch:
            raise rd.fail(f"{ep}.slots", "empty: name at least one follower")
        schedule.append(SlotChange(at=at, slots=ch))
    return tuple(schedule)


def _formation_roles(rd: _Reader, formation: FormationConfig, robots: list[RobotConfig]) -> list[RobotConfig]:
    """Every robot's role from ``formation.leader`` (a given role must agree); every follower has a slot."""
    out = []
    for i, r in enumerate(robots):
        want = "leader" if r.id == formation.leader else "follower"
        if r.role is not None and r.role != want:
            raise rd.fail(f"robots[{i}].role", f"robot {r.id} is {r.role} but formation.leader is {formation.leader}")
        if want == "follower" and r.id not in formation.slots:
            raise rd.fail("formation.slots", f"follower {r.id} has no slot")
        out.append(replace(r, role=want) if r.role is None else r)
    return out


def _arrival_peers(rd: _Reader, robots: list[RobotConfig]) -> None:
    for i, r in enumerate(robots):
        if r.goal is None:
            raise rd.fail(f"robots[{i}].goal", "an arrival-time task needs a goal for every robot")
        if r.role is not None:
            raise rd.fail(f"robots[{i}].role", "an arrival-time task has peers only: leave role out")


def _success(rd: _Reader, value: Any) -> SuccessConfig:
    s = rd.mapping(value, "success", {"goal_tolerance", "max_time", "no_collisions", "settle_s"})
    return SuccessConfig(
        goal_tolerance=rd.number(s.get("goal_tolerance", 0.5), "success.goal_tolerance", 0.0, lo_open=True),
        max_time=rd.number(s["max_time"], "success.max_time", 0.0, lo_open=True) if "max_time" in s else None,
        no_collisions=rd.boolean(s.get("no_collisions", True), "success.no_collisions"),
        settle_s=rd.number(s.get("settle_s", 10.0), "success.settle_s", 0.0, 600.0),
    )


def _bench(rd: _Reader, value: Any) -> BenchConfig:
    if value is None:
        return BenchConfig()
    b = rd.mapping(value, "bench", {"policies", "reference"})
    names = policy_names()
    pols = b.get("policies", list(names))
    if not isinstance(pols, list) or not pols:
        raise rd.fail("bench.policies", f"expected a non-empty list, got {_kind(pols)}")
    return BenchConfig(policies=tuple(rd.choice(x, f"bench.policies[{i}]", names) for i, x in enumerate(pols)),
                       reference=str(b.get("reference", "")))


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise ScenarioError(f"{p}: cannot read: {e.strerror or e}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        raise ScenarioError(f"{p}: {where}not valid YAML ({getattr(e, 'problem', None) or e})") from None
    return parse_scenario(data, str(p))


BURST_P_BAD_GOOD = 0.3  # bursts of about 1 / 0.3 = 3.3 messages on average


def burst_with_mean(loss: float) -> dict | None:
    """A Gilbert-Elliott channel losing every message in the bad state, with the given mean loss:
    p_bad = p_gb / (p_gb + p_bg) = loss  ->  p_gb = loss p_bg / (1 - loss)."""
    if loss <= 0.0:
        return None
    if loss >= 1.0:
        return {"p_good_bad": 1.0, "p_bad_good": 0.0, "loss_bad": 1.0}
    return {"p_good_bad": min(1.0, loss * BURST_P_BAD_GOOD / (1.0 - loss)), "p_bad_good": BURST_P_BAD_GOOD, "loss_bad": 1.0}


def with_overrides(sc: Scenario, *, policy: str | None = None, driver: str | None = None, loss: float | None = None,
                   latency_ms: float | None = None, seed: int | None = None, duration: float | None = None,
                   burst_loss: float | None = None) -> Scenario:
    """Apply the command-line overrides of ``stack-fleet run`` (and the sweeps of ``stack-fleet bench``)
    to the raw YAML and validate again. ``burst_loss``: Gilbert-Elliott loss with that mean."""
    raw = _deepcopy(sc.raw)
    if burst_loss is not None:
        raw["comm"] = dict(raw.get("comm") or {}) | {"loss": 0.0, "burst": burst_with_mean(burst_loss)}
    if policy is not None:
        _check_flag("--policy", policy, policy_names())
        for r in raw["robots"]:
            r["policy"] = policy
        raw["robot"] = dict(raw.get("robot") or {}) | {"policy": policy}
    if driver is not None:
        _check_flag("--driver", driver, driver_names())
        for r in raw["robots"]:
            r["driver"] = driver
    if loss is not None or latency_ms is not None:
        comm = dict(raw.get("comm") or {})
        if loss is not None:
            comm["loss"] = loss
            comm["burst"] = None  # --loss asks for Bernoulli loss at that rate
        if latency_ms is not None:
            comm["latency_ms"] = latency_ms
        raw["comm"] = comm
    if seed is not None:
        raw["seed"] = seed
    if duration is not None:
        raw["duration"] = duration
    return parse_scenario(raw, sc.source)


def with_driver_settings(sc: Scenario, settings: dict[int, dict[str, Any]]) -> Scenario:
    """The scenario with more driver settings for some robots (``{id: {key: value}}``, for each robot's own
    driver), over what the scenario gave them: how the fleet tells agents where their simulated device is."""
    raw = _deepcopy(sc.raw)
    for r in raw["robots"]:
        extra = settings.get(r["id"])
        if extra:
            robot = sc.robot(r["id"])
            r[robot.driver] = dict(robot.driver_params.get(robot.driver, {})) | extra
    return parse_scenario(raw, sc.source)


def with_lidar_settings(sc: Scenario, extra: dict[int, dict[str, Any]]) -> Scenario:
    """The scenario with more settings for some robots' lidar sources (``{id: {key: value}}``, under each
    robot's own ``lidar.<source>``): how the fleet tells agents where their simulated lidar is."""
    raw = _deepcopy(sc.raw)
    for r in raw["robots"]:
        more = extra.get(r["id"])
        if more:
            source = sc.robot(r["id"]).lidar.source
            block = r["lidar"] = dict(r.get("lidar") or {})
            block[source] = dict(block.get(source) or {}) | more
    return parse_scenario(raw, sc.source)


def _check_flag(flag: str, value: str, options: tuple[str, ...]) -> None:
    if value not in options:
        raise ScenarioError(f"{flag}: expected one of {', '.join(options)}, got {value!r}")


def _deepcopy(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _deepcopy(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_deepcopy(v) for v in x]
    return x


def fix_due(robot: RobotConfig, step: int, dt: float) -> bool:
    """Whether the robot's (simulated) position fix is sent at this step: every round(1 / (rate dt)) steps."""
    return robot.fix is not None and step % max(1, round(1.0 / (robot.fix[0] * dt))) == 0



def summary(sc: Scenario) -> dict:
    """The resolved config as plain data, for logs."""
    return asdict(sc) | {"raw": None}


FAULT_KINDS = ("kill", "freeze", "restart")


def parse_fault_at(text: str) -> tuple[int, float]:
    """``ID@SECONDS`` of ``--kill/--freeze/--restart`` (ValueError with the expected form)."""
    import re

    m = re.fullmatch(r"(\d+)@(\d+(?:\.\d*)?)", text.strip())
    if not m:
        raise ValueError(f"expected ID@SECONDS, e.g. 2@30, got {text!r}")
    return int(m.group(1)), float(m.group(2))
