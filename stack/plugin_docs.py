"""Markdown tables of every plugin's settings, made from the registries (``python -m stack.plugins``):
``docs/settings.md`` is this text, and a test keeps the two equal."""

from __future__ import annotations

import math
from dataclasses import MISSING

from . import settings
from .plugins import Plugin, Registry, registries

HEADER = ("# Plugin settings\n\n"
          "Generated from the plugin registries by `python -m stack.plugins` (do not edit by hand: "
          "`tests/test_registry.py` checks this file against them). Each policy's settings are the "
          "scenario block `robot.<key>` (also per robot, over the `robot:` defaults); each driver's "
          "are `robot.<driver>`. Unknown keys are errors.\n")


def _value(v) -> str:
    if v is MISSING:
        return "required"
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.6g}" if math.isfinite(v) else str(v)
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_value(x)}" for k, x in v.items()) + "}"
    return str(v)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def plugin_table(kind: str, rec: Plugin) -> str:
    """One plugin's heading, its record and its settings table."""
    block = {"policies": f"`robot.{rec.settings_key}` ", "drivers": f"`robot.{rec.name}` ",
             "lidars": f"`robot.lidar.{rec.name}` "}.get(kind, "")
    lines = [f"### `{rec.name}`", ""]
    if rec.summary:
        lines += [rec.summary + ".", ""]
    lines.append("Settings: " + (f"{block}(`{rec.config}`)" if rec.config else "none") + f"; factory `{rec.factory}`"
                 + (f"; simulated device `{rec.device}`" if rec.device else "") + ".")
    cls = rec.config_class()
    if cls is not None and kind == "policies" and rec.key and rec.key != rec.name:
        lines += ["", f"The same settings as the policy that owns `robot.{rec.key}`."]
    elif cls is not None:
        lines += _table(cls)
    if kind == "lidars" and rec.device:
        lines += ["", "Its simulated device's settings (`robot.lidar.device`, simulation only):"]
        lines += _table(rec.device_class().config_class)
    return "\n".join(lines) + "\n"


def _table(cls) -> list[str]:
    lines = ["", "| key | default | accepts | meaning |", "| --- | --- | --- | --- |"]
    for key, default, accepted, doc in settings.rows(cls):
        lines.append(f"| `{key}` | {_cell(_value(default))} | {_cell(accepted)} | {_cell(doc)} |")
    return lines


LIDARS_INTRO = ("`robot.lidar.source` (also per robot) picks the robot's lidar source; its settings are "
                "`robot.lidar.<source>`. `robot.lidar.mount: [x, y, yaw_deg]` is the sensor's pose on the robot "
                "(x forward, y left from the robot's centre; default `[0, 0, 0]`): each sample is moved to the "
                "robot's centre and the scan resampled to the `beams` over `fov_deg` the policy was built for "
                "(nearest valid sample in bearing within 1.5 sample spacings, else `range`). In simulation the "
                "world hosts the source's simulated device, at its own rate and beam layout.\n")


def kind_section(kind: str, reg: Registry) -> str:
    parts = [f"## {kind.capitalize()}\n", f"Registered: {', '.join(f'`{n}`' for n in reg)}.\n"]
    if kind == "lidars":
        parts.append(LIDARS_INTRO)
    parts += [plugin_table(kind, reg[name]) for name in reg]
    return "\n".join(parts)


ROBOT_BLOCKS = (("ros_graph", "stack.agents.ros_graph:RosGraphConfig",
                 "The agent's estimate, formation slot and goal as ROS 2 topics (docs/ros2.md); off by default"),)
"""Per-robot settings blocks that belong to no plugin: (key, ``module:Class``, summary)."""


def robot_section() -> str:
    """The per-robot blocks of no plugin (``robot.<key>``, also per robot over the ``robot:`` defaults)."""
    from .plugins import load

    parts = ["## Robot settings\n"]
    for key, ref, summary in ROBOT_BLOCKS:
        lines = [f"### `robot.{key}`", "", summary + ".", "", f"Settings: `robot.{key}` (`{ref}`).", "",
                 "| key | default | accepts | meaning |", "| --- | --- | --- | --- |"]
        for k, default, accepted, doc in settings.rows(load(ref)):
            lines.append(f"| `{k}` | {_cell(_value(default))} | {_cell(accepted)} | {_cell(doc)} |")
        parts.append("\n".join(lines) + "\n")
    return "\n".join(parts)


def settings_markdown(only_builtin: bool = True) -> str:
    """The whole ``docs/settings.md``: every kind, every plugin (the built-ins: out-of-tree plugins vary
    by installation), then the robot settings of no plugin."""
    out = [HEADER]
    for kind, reg in registries().items():
        out.append(kind_section(kind, reg.builtins() if only_builtin else reg))
    out.append(robot_section())
    return "\n".join(out)
