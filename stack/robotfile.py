"""A robot's own settings file, layered over the fleet's mission file.

The mission file is the scenario every robot of a fleet shares: formation, ids and roles, comm, the site
datum (``world:`` and ``success:`` are the simulated world's and the simulated run's: optional, never read
by a robot). A robot adds its own file (``stack-agent --id 2 --scenario mission.yaml --robot robot.yaml``)
whose keys are the keys of its ``robots[i]`` entry: driver and driver block, lidar, limits, policy, start
pose, ``odom_origin``, ``fix``... Each key of the robot file replaces the entry's; a mapping (``can:``,
``lidar:``, ``device:``) is merged key by key over the entry's, which is itself layered over the mission's
``robot:`` defaults as in any scenario. Unknown keys and bad values are one-line errors naming the robot
file and the key's path in it (``robot.yaml: can.bogus: unknown field (allowed: ...)``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from .scenario import RobotConfig, Scenario, ScenarioError, check_robot_entry, load_scenario, parse_scenario


def read_robot_file(path: str | Path) -> dict:
    """The robot file as a checked mapping (empty file: no settings)."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except OSError as e:
        raise ScenarioError(f"{p}: cannot read: {e.strerror or e}") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        raise ScenarioError(f"{p}: {where}not valid YAML ({getattr(e, 'problem', None) or e})") from None
    data = {} if data is None else data
    check_robot_entry(data, str(p))
    return data


def merge(base: Any, over: Any) -> Any:
    """``over`` layered on ``base``: mappings key by key (recursively), anything else replaced."""
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for k, v in over.items():
            out[k] = merge(base.get(k), v) if k in base else v
        return out
    return over


def layer(raw: dict, robot_id: int, robot: dict, source: str = "<robot>") -> dict:
    """The mission's raw YAML with robot ``robot_id``'s entry under ``robots:`` layered with ``robot``."""
    if "id" in robot and robot["id"] != robot_id:
        raise ScenarioError(f"{source}: id: {robot['id']}, but this robot is --id {robot_id}")
    entries = raw.get("robots") if isinstance(raw.get("robots"), list) else []
    hits = [i for i, r in enumerate(entries) if isinstance(r, dict) and r.get("id") == robot_id]
    if not hits:
        raise ScenarioError(f"{source}: the mission has no robot with id {robot_id}")
    out = dict(raw)
    out["robots"] = [merge(r, robot) if i == hits[0] else r for i, r in enumerate(entries)]
    return out


def load_mission(mission: str | Path, robot_id: int, robot_file: str | Path | None = None) -> Scenario:
    """The mission file with this robot's own file over its entry (just the mission without one)."""
    sc = load_scenario(mission)
    if robot_file is None:
        return sc
    sc.robot(robot_id)  # the mission names this robot (its own one-line error otherwise)
    robot = read_robot_file(robot_file)
    raw = layer(sc.raw, robot_id, robot, str(robot_file))
    try:
        return parse_scenario(raw, sc.source)
    except ScenarioError as e:  # the mission alone was fine: the robot file made it wrong
        raise ScenarioError(f"{robot_file}: over {e}") from None


def describe(robot: RobotConfig, driver: str | None = None) -> str:
    """The resolved settings a robot runs with, on one line (logged at start)."""
    name = driver or robot.driver
    lid = robot.lidar
    x, y, yaw = robot.pose
    parts = [f"role {robot.role or 'peer'}", f"policy {robot.policy}", f"driver {name} {robot.driver_params.get(name, {})}",
             f"lidar {getattr(lid, 'source', 'world')} {lid.beams} beams over {math.degrees(lid.fov):g} deg to {lid.range:g} m",
             f"v_max {robot.v_max:g} m/s, w_max {robot.w_max:g} rad/s, radius {robot.radius:g} m, cmd_timeout {robot.cmd_timeout:g} s",
             f"start pose ({x:g}, {y:g}, {math.degrees(yaw):g} deg), odom_origin {robot.odom_origin}",
             f"fix {'none' if robot.fix is None else f'{robot.fix[0]:g} Hz, std {robot.fix[1]:g} m'}"]
    return "; ".join(parts)
