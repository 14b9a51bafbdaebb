"""What our messages look like in Foxglove: topic names, JSON schemas and the builders that turn our wire
messages (and the scenario) into Foxglove messages (``foxglove.messages``), for the fleet's recorder and a
robot's own view alike (``stack.fleet.viz_messages`` adds the fleet's ground-truth builders).

Pure functions, no I/O: the writers call them on their writer threads, ``stack.fleet.replay`` reads the topics back.
Frames: ``world`` (fixed), ``robot_<id>`` (true pose, from the world's truth) and ``robot_<id>/estimate``
(the robot's own estimate, from its state). Times are nanoseconds: sim time in lock-step, wall time in real time.
"""

from __future__ import annotations

import json
import math

import numpy as np
from foxglove import Schema
from foxglove.messages import (ArrowPrimitive, Color, CubePrimitive, CylinderPrimitive, FrameTransform, FrameTransforms,
                               KeyValuePair, LaserScan, LinePrimitive, LinePrimitiveLineType, Point3, Pose, PoseInFrame,
                               Quaternion, SceneEntity, SceneEntityDeletion, SceneEntityDeletionType, SceneUpdate,
                               TextPrimitive, Timestamp, Vector3)

from ..comm.messages import Scan, State
from ..scenario import Scenario

WORLD = "world"
TOPICS = {
    "clock": "/clock", "tf": "/tf", "tf_estimate": "/tf_estimate", "obstacles": "/scene/obstacles",
    "robots": "/scene/robots", "slots": "/formation/slots", "links": "/comm/links", "metrics": "/metrics",
    "events": "/events",
}
ROBOT_TOPICS = ("pose", "estimate", "scan", "cmd_vel", "state", "diag", "virtual_scan")
"""``virtual_scan``: a real robot's virtual returns (``robot.lidar.virtual``), apart from its scan."""
LINK_COLORS = {"delivered": (0.1, 0.7, 0.2), "dropped_loss": (1.0, 0.6, 0.0), "dropped_range": (0.9, 0.1, 0.1)}


def robot_topic(rid: int, what: str) -> str:
    """``/robot_<id>/<what>``, ``what`` one of :data:`ROBOT_TOPICS`."""
    return f"/robot_{rid}/{what}"


def frame(rid: int, estimate: bool = False) -> str:
    return f"robot_{rid}/estimate" if estimate else f"robot_{rid}"


def _field(spec) -> dict:
    """A property's JSON schema: a type name (``"number"``), ``[item]`` (an array of item), ``{"*": value}``
    (an object whose keys are free and whose values are value) or ``{name: spec}`` (an object with those
    properties). Complete all the way down: a viewer that meets an array without ``items`` cannot read the topic."""
    if isinstance(spec, str):
        return {"type": spec}
    if isinstance(spec, list):
        return {"type": "array", "items": _field(spec[0])}
    if set(spec) == {"*"}:
        return {"type": "object", "properties": {}, "additionalProperties": _field(spec["*"])}
    return {"type": "object", "properties": {k: _field(v) for k, v in spec.items()}}


def _obj(name: str, fields: dict) -> Schema:
    doc = {"title": name, **_field(fields)}
    return Schema(name=name, encoding="jsonschema", data=json.dumps(doc).encode())


LINK_COUNTS = {"delivered": "integer", "dropped_range": "integer", "dropped_loss": "integer"}
JSON_SCHEMAS = {
    "clock": _obj("stack.Clock", {"step": "integer", "t": "number", "dt": "number", "lockstep": "boolean",
                                  "answered": ["integer"], "dead": ["integer"]}),
    "metrics": _obj("stack.Metrics", {"step": "integer", "t": "number", "formation_error_rms": "number",
                                      "formation_error_max": "number", "min_robot_distance": "number",
                                      "min_obstacle_distance": "number", "leader": "integer",
                                      "errors": {"*": "number"}}),
    "cmd_vel": _obj("stack.CmdVel", {"id": "integer", "step": "integer", "stamp": "number", "v": "number", "w": "number"}),
    "state": _obj("stack.State", {"id": "integer", "step": "integer", "role": "string", "policy": "string",
                                  "situation": "string", "x": "number", "y": "number", "yaw": "number", "v": "number",
                                  "w": "number", "cov_trace": "number", "d_goal": "number", "seq": "integer",
                                  "stamp": "number", "wall": "number"}),
    "diag": _obj("stack.Diag", {"id": "integer", "step": "integer", "state": "string", "sent": "integer",
                                "received": "integer", "delivered": "integer", "dropped_loss": "integer",
                                "dropped_range": "integer", "malformed": "integer", "fault": "string",
                                "led_since": "number", "plan_age_s": "number", "plan_in_flight_s": "number",
                                "plan_ms_p99": "number", "plan_ms_max": "number", "plans": "integer"}),
    "step_io": _obj("stack.StepRecord", {  # stack.agents.steplog: every input of a control step and what it returned
        "version": "integer", "id": "integer", "n": "integer", "step": "integer", "t": "number", "t_run": "number",
        "now": "number", "odometry": [{"v": "number", "w": "number", "t": "number", "wz_imu": "number",
                                       "pose": ["number"], "fix": ["number"]}],
        "scan": {"id": "integer", "step": "integer", "stamp": "number", "angle_min": "number",
                 "angle_increment": "number", "range_max": "number", "ranges": ["number"]},
        "scan_same": "boolean", "scan_t": "number", "fixes": [{"x": "number", "y": "number", "std": "number"}],
        "states": [{"id": "integer", "role": "string", "seq": "integer", "stamp": "number", "x": "number", "y": "number",
                    "yaw": "number", "v": "number", "w": "number", "step": "integer", "cov_trace": "number",
                    "situation": "string", "wall": "number", "d_goal": "number"}],
        "state_refs": {"id": ["integer"], "seq": ["integer"], "stamp": ["number"]},
        "dead": ["integer"], "held": "string", "goal": ["number"],
        "out": {"v": "number", "w": "number", "pose": ["number"], "situation": "string", "cov_trace": "number",
                "d_goal": "number", "stale": "string", "target": ["number"], "role": "string", "guard_caps": "integer",
                "guard_slides": "integer", "heard": ["integer"]},
        "cmd": ["number"],
        "setup": {"version": "integer", "robot": "integer", "scenario": "string", "source": "string", "policy": "string",
                  "seed": "integer", "step_config": {
                      "odom_stale_s": "number", "lidar_stale_s": "number", "max_gap_s": "number", "odom_origin": "string",
                      "guard": {"margin": "number", "decel": "number", "lag_s": "number", "enabled": "boolean",
                                "slide_after_s": "number", "slide_free": "number"}}, "lockstep": "boolean", "driver": "string",
                  "stack": "string"}}),
}


def diag_doc(d) -> dict:
    """The ``diag`` topic's document of an agent's ``Diag`` (the fleet's recording and the agent's live view alike):
    its counters, and where it plans beside the control step the plan's age, how long the plan in flight has run
    [s] and the compute times [ms]."""
    doc = {k: getattr(d, k) for k in ("id", "step", "state", "sent", "received", "delivered", "dropped_loss",
                                      "dropped_range", "malformed", "fault")}
    if d.led_since is not None:
        doc["led_since"] = d.led_since
    if d.planner:
        p = d.planner
        for k, v in (("plans", p.get("adopted")), ("plan_age_s", p.get("age_s")),
                     ("plan_in_flight_s", p.get("in_flight_s")), ("plan_ms_p99", p.get("ms_p99")),
                     ("plan_ms_max", p.get("ms_max"))):
            if v is not None:
                doc[k] = v
    return doc


def ts(ns: int) -> Timestamp:
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def quat(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def pose(x: float, y: float, yaw: float = 0.0, z: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=quat(yaw))


_IDENTITY = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
_WHITE = Color(r=1.0, g=1.0, b=1.0, a=1.0)
_BODY = Color(r=0.15, g=0.4, b=0.85, a=0.8)
_ESTIMATE = Color(r=1.0, g=0.85, b=0.1, a=0.35)
_SLOT = Color(r=0.2, g=0.9, b=0.9, a=0.4)
_REAL = Color(r=0.1, g=0.75, b=0.3, a=0.9)  # a real robot's body (where its pose source puts it)
_STALE = Color(r=0.5, g=0.5, b=0.5, a=0.5)  # ... whose pose source went stale


def _replace_all(ns: int, entities: list[SceneEntity]) -> SceneUpdate:
    """A scene that replaces the topic's previous one whole (entities that are gone now disappear)."""
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=ts(ns), type=SceneEntityDeletionType.All, id="")],
                       entities=entities)


def _color(rgb: tuple[float, float, float], a: float = 1.0) -> Color:
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=a)


def estimate_transform(m: State, ns: int) -> FrameTransforms:
    """world -> robot_<id>/estimate: where the robot believes it is (from its state)."""
    return estimate_frame(m.id, m.x, m.y, m.yaw, ns)


def estimate_frame(rid: int, x: float, y: float, yaw: float, ns: int) -> FrameTransforms:
    """world -> robot_<rid>/estimate at the estimate (x, y, yaw)."""
    return FrameTransforms(transforms=[FrameTransform(timestamp=ts(ns), parent_frame_id=WORLD,
                                                      child_frame_id=frame(rid, estimate=True),
                                                      translation=Vector3(x=x, y=y, z=0.0), rotation=quat(yaw))])


def pose_in_world(x: float, y: float, yaw: float, ns: int) -> PoseInFrame:
    return PoseInFrame(timestamp=ts(ns), frame_id=WORLD, pose=pose(x, y, yaw))


NO_RETURN = 0.98
"""Beams that read at least this fraction of ``range_max`` saw nothing (the reading is range_max plus noise):
written as +inf, the REP 117 convention viewers draw as no return."""


def laser_scan(m: Scan, ns: int, frame_id: str | None = None) -> LaserScan:
    """The scan in the robot's true frame (the world simulated it from there), or in ``frame_id`` (a robot's
    own view: its estimate's frame)."""
    r = np.asarray(m.ranges, dtype=float)
    ranges = np.where(r < NO_RETURN * m.range_max, r, np.inf).tolist()
    return LaserScan(timestamp=ts(ns), frame_id=frame_id or frame(m.id), pose=pose(0.0, 0.0), start_angle=m.angle_min,
                     end_angle=m.angle_min + m.angle_increment * (len(ranges) - 1), ranges=ranges, intensities=[])


def obstacles_scene(sc: Scenario, ns: int) -> SceneUpdate:
    """Cylinders, boxes and walls (1 m tall), one entity each, in the world frame."""
    entities = []
    solid, virtual = _color((0.55, 0.35, 0.3), 0.9), _color((0.6, 0.4, 0.9), 0.45)  # virtual: only in the world
    for i, o in enumerate(sc.obstacles):
        grey = virtual if o.virtual else solid
        if o.type == "cylinder":
            kw = {"cylinders": [CylinderPrimitive(pose=pose(o.x, o.y, 0.0, 0.5), bottom_scale=1.0, top_scale=1.0,
                                                  size=Vector3(x=2 * o.radius, y=2 * o.radius, z=1.0), color=grey)]}
        else:
            cx, cy, hx, hy, yaw = o.as_box()
            kw = {"cubes": [CubePrimitive(pose=pose(cx, cy, yaw, 0.5), size=Vector3(x=2 * hx, y=2 * hy, z=1.0), color=grey)]}
        entities.append(SceneEntity(timestamp=ts(ns), frame_id=WORLD, id=f"obstacle-{i}", metadata=[], **kw))
    return SceneUpdate(deletions=[], entities=entities)


def slots_scene(sc: Scenario, targets: dict[int, tuple[float, float]], ns: int) -> SceneUpdate:
    """The followers' slots now: one entity, a flat ring per slot (its id in the entity's metadata, in order)."""
    rings = [CylinderPrimitive(pose=Pose(position=Vector3(x=x, y=y, z=0.01), orientation=_IDENTITY),
                               size=Vector3(x=2 * sc.robot(rid).radius, y=2 * sc.robot(rid).radius, z=0.02),
                               bottom_scale=1.0, top_scale=1.0, color=_SLOT) for rid, (x, y) in targets.items()]
    entity = SceneEntity(timestamp=ts(ns), frame_id=WORLD, id="slots", cylinders=rings,
                         metadata=[KeyValuePair(key="robots", value=",".join(str(r) for r in targets))])
    return _replace_all(ns, [entity])


def links_scene(window: dict[tuple[int, int], dict[str, int]], where: dict[int, tuple[float, float]], ns: int) -> SceneUpdate:
    """The comm graph over the last window: a line sender -> receiver (true positions) per link, green if
    everything got through, orange if some was lost, red if some was out of range; counts in its metadata."""
    entities = []
    for (sender, receiver), n in sorted(window.items()):
        if sender not in where or receiver not in where or not any(n.values()):
            continue
        worst = "dropped_range" if n["dropped_range"] else "dropped_loss" if n["dropped_loss"] else "delivered"
        (x0, y0), (x1, y1) = where[sender], where[receiver]
        entities.append(SceneEntity(
            timestamp=ts(ns), frame_id=WORLD, id=f"link-{sender}-{receiver}",
            metadata=[KeyValuePair(key=k, value=str(v)) for k, v in n.items()] + [KeyValuePair(key="worst", value=worst)],
            lines=[LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=pose(0.0, 0.0), thickness=2.0,
                                 scale_invariant=True, points=[Point3(x=x0, y=y0, z=0.4), Point3(x=x1, y=y1, z=0.4)],
                                 color=_color(LINK_COLORS[worst], 0.8), colors=[], indices=[])]))
    return _replace_all(ns, entities)


# --- a robot's own view (``stack-agent --record / --viz``): what the robot itself knows ----------------------
AGENT_TOPICS = ("estimate", "scan", "cmd_vel", "state", "diag", "covariance", "decision", "heard", "scene", "links")
"""Per robot, in its own recording: its estimate, its scan as received (in the estimate's frame), its command,
its state and diag (the fleet's schemas), and: the covariance, the decision (situation, policy, target, goal),
the neighbours it heard and what its radio model dropped, a scene of all that, and its links this step."""
AGENT_SCHEMAS = {
    "covariance": _obj("stack.Covariance", {"step": "integer", "t": "number", "cov": ["number"], "sigma_x": "number",
                                            "sigma_y": "number", "sigma_yaw": "number", "cov_trace": "number"}),
    "decision": _obj("stack.Decision", {"step": "integer", "t": "number", "role": "string", "situation": "string",
                                        "policy": "string", "target": ["number"], "goal": ["number"], "stale": "string",
                                        "led_since": "number"}),
    "heard": _obj("stack.Heard", {"step": "integer", "t": "number",
                                  "neighbours": [{"id": "integer", "role": "string", "x": "number", "y": "number",
                                                  "yaw": "number", "v": "number", "w": "number", "age": "number"}],
                                  "gone": ["integer"], "delivered": "integer", "dropped_range": "integer",
                                  "dropped_loss": "integer", "rejected": "integer", "links": {"*": LINK_COUNTS}}),
}
_GOAL = Color(r=0.2, g=0.8, b=0.2, a=0.8)
_HEARD = Color(r=0.6, g=0.6, b=0.6, a=0.5)


def covariance_ellipse(x: float, y: float, cov_xy, ns: int, floor: float = 0.02) -> SceneEntity:
    """The 1-sigma ellipse of the estimate's (x, y) covariance, a flat disc in ``world`` (axes at least ``floor``)."""
    vals, vecs = np.linalg.eigh(np.asarray(cov_xy, dtype=float).reshape(2, 2))
    minor, major = (max(math.sqrt(max(v, 0.0)), floor) for v in vals)
    angle = math.atan2(vecs[1, 1], vecs[0, 1])  # the major axis
    return SceneEntity(timestamp=ts(ns), frame_id=WORLD, id="covariance", metadata=[], cylinders=[CylinderPrimitive(
        pose=pose(x, y, angle, 0.02), size=Vector3(x=2 * major, y=2 * minor, z=0.04), bottom_scale=1.0, top_scale=1.0,
        color=_ESTIMATE)])


def agent_scene(rid: int, radius: float, est: tuple[float, float, float], cov_xy, target, goal,
                heard: list[tuple[int, float, float]], ns: int) -> SceneUpdate:
    """A robot's own picture: its body on its estimate's frame, the covariance ellipse, where it steers
    (``target``: the slot, the goal, an escape waypoint) and the mission's ``goal``, and the neighbours it
    heard at their reported positions (``heard``: (id, x, y))."""
    r = radius
    entities = [SceneEntity(
        timestamp=ts(ns), frame_id=frame(rid, estimate=True), id=f"robot-{rid}", frame_locked=True, metadata=[],
        cylinders=[CylinderPrimitive(pose=pose(0.0, 0.0, 0.0, 0.15), size=Vector3(x=2 * r, y=2 * r, z=0.3),
                                     bottom_scale=1.0, top_scale=1.0, color=_BODY)],
        arrows=[ArrowPrimitive(pose=pose(0.0, 0.0, 0.0, 0.35), shaft_length=r, shaft_diameter=0.08, head_length=0.25,
                               head_diameter=0.2, color=_WHITE)]),
        covariance_ellipse(est[0], est[1], cov_xy, ns)]
    for name, xy, color, size in (("target", target, _SLOT, 2 * r), ("goal", goal, _GOAL, 0.4)):
        if xy is not None:
            entities.append(SceneEntity(timestamp=ts(ns), frame_id=WORLD, id=name, metadata=[], cylinders=[CylinderPrimitive(
                pose=pose(xy[0], xy[1], 0.0, 0.01), size=Vector3(x=size, y=size, z=0.02), bottom_scale=1.0, top_scale=1.0,
                color=color)]))
    if heard:
        entities.append(SceneEntity(
            timestamp=ts(ns), frame_id=WORLD, id="heard", metadata=[KeyValuePair(key="robots", value=",".join(str(h[0]) for h in heard))],
            cylinders=[CylinderPrimitive(pose=pose(x, y, 0.0, 0.15), size=Vector3(x=2 * r, y=2 * r, z=0.3), bottom_scale=1.0,
                                         top_scale=1.0, color=_HEARD) for _, x, y in heard],
            texts=[TextPrimitive(pose=pose(x, y, 0.0, 0.8), billboard=True, font_size=14.0, scale_invariant=True,
                                 color=_WHITE, text=str(nid)) for nid, x, y in heard]))
    return _replace_all(ns, entities)
