"""What a fleet's Zenoh traffic looks like in Foxglove: topic names, JSON schemas and the builders that
turn our wire messages (and the scenario) into Foxglove messages (``foxglove.messages``).

Pure functions, no I/O: :mod:`.record` calls them on its writer thread, :mod:`.replay` reads the topics back.
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

from ..comm.messages import Scan, State, Truth
from ..scenario import Scenario, slot_position
from ..sim_bridge.geometry import distance_to_obstacles

WORLD = "world"
TOPICS = {
    "clock": "/clock", "tf": "/tf", "tf_estimate": "/tf_estimate", "obstacles": "/scene/obstacles",
    "robots": "/scene/robots", "slots": "/formation/slots", "links": "/comm/links", "metrics": "/metrics",
    "events": "/events",
}
ROBOT_TOPICS = ("pose", "estimate", "scan", "cmd_vel", "state", "diag")
LINK_COLORS = {"delivered": (0.1, 0.7, 0.2), "dropped_loss": (1.0, 0.6, 0.0), "dropped_range": (0.9, 0.1, 0.1)}


def robot_topic(rid: int, what: str) -> str:
    """``/robot_<id>/<what>``, ``what`` one of :data:`ROBOT_TOPICS`."""
    return f"/robot_{rid}/{what}"


def frame(rid: int, estimate: bool = False) -> str:
    return f"robot_{rid}/estimate" if estimate else f"robot_{rid}"


def _obj(name: str, fields: dict[str, str]) -> Schema:
    doc = {"title": name, "type": "object", "properties": {k: {"type": v} for k, v in fields.items()}}
    return Schema(name=name, encoding="jsonschema", data=json.dumps(doc).encode())


JSON_SCHEMAS = {
    "clock": _obj("stack.Clock", {"step": "integer", "t": "number", "dt": "number", "lockstep": "boolean",
                                  "answered": "array", "dead": "array"}),
    "metrics": _obj("stack.Metrics", {"step": "integer", "t": "number", "formation_error_rms": "number",
                                      "formation_error_max": "number", "min_robot_distance": "number",
                                      "min_obstacle_distance": "number", "leader": "integer", "errors": "object"}),
    "cmd_vel": _obj("stack.CmdVel", {"id": "integer", "step": "integer", "stamp": "number", "v": "number", "w": "number"}),
    "state": _obj("stack.State", {"id": "integer", "step": "integer", "role": "string", "policy": "string",
                                  "situation": "string", "x": "number", "y": "number", "yaw": "number", "v": "number",
                                  "w": "number", "cov_trace": "number", "d_goal": "number"}),
    "diag": _obj("stack.Diag", {"id": "integer", "step": "integer", "state": "string", "sent": "integer",
                                "received": "integer", "delivered": "integer", "dropped_loss": "integer",
                                "dropped_range": "integer", "malformed": "integer", "fault": "string",
                                "led_since": "number"}),
}


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


def _replace_all(ns: int, entities: list[SceneEntity]) -> SceneUpdate:
    """A scene that replaces the topic's previous one whole (entities that are gone now disappear)."""
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=ts(ns), type=SceneEntityDeletionType.All, id="")],
                       entities=entities)


def _color(rgb: tuple[float, float, float], a: float = 1.0) -> Color:
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=a)


def truth_transforms(m: Truth, ns: int) -> FrameTransforms:
    """world -> robot_<id>: every robot's true pose at this step."""
    return FrameTransforms(transforms=[
        FrameTransform(timestamp=ts(ns), parent_frame_id=WORLD, child_frame_id=frame(rid),
                       translation=Vector3(x=x, y=y, z=0.0), rotation=quat(yaw))
        for rid, x, y, yaw in zip(m.ids, m.x, m.y, m.yaw)])


def estimate_transform(m: State, ns: int) -> FrameTransforms:
    """world -> robot_<id>/estimate: where the robot believes it is."""
    return FrameTransforms(transforms=[FrameTransform(timestamp=ts(ns), parent_frame_id=WORLD,
                                                      child_frame_id=frame(m.id, estimate=True),
                                                      translation=Vector3(x=m.x, y=m.y, z=0.0), rotation=quat(m.yaw))])


def pose_in_world(x: float, y: float, yaw: float, ns: int) -> PoseInFrame:
    return PoseInFrame(timestamp=ts(ns), frame_id=WORLD, pose=pose(x, y, yaw))


NO_RETURN = 0.98
"""Beams that read at least this fraction of ``range_max`` saw nothing (the reading is range_max plus noise):
written as +inf, the REP 117 convention viewers draw as no return."""


def laser_scan(m: Scan, ns: int) -> LaserScan:
    """The scan in the robot's own (true) frame: the world simulated it from there."""
    r = np.asarray(m.ranges, dtype=float)
    ranges = np.where(r < NO_RETURN * m.range_max, r, np.inf).tolist()
    return LaserScan(timestamp=ts(ns), frame_id=frame(m.id), pose=pose(0.0, 0.0), start_angle=m.angle_min,
                     end_angle=m.angle_min + m.angle_increment * (len(ranges) - 1), ranges=ranges, intensities=[])


def obstacles_scene(sc: Scenario, ns: int) -> SceneUpdate:
    """Cylinders, boxes and walls (1 m tall), one entity each, in the world frame."""
    entities = []
    grey = _color((0.55, 0.35, 0.3), 0.9)
    for i, o in enumerate(sc.obstacles):
        if o.type == "cylinder":
            kw = {"cylinders": [CylinderPrimitive(pose=pose(o.x, o.y, 0.0, 0.5), bottom_scale=1.0, top_scale=1.0,
                                                  size=Vector3(x=2 * o.radius, y=2 * o.radius, z=1.0), color=grey)]}
        else:
            cx, cy, hx, hy, yaw = o.as_box()
            kw = {"cubes": [CubePrimitive(pose=pose(cx, cy, yaw, 0.5), size=Vector3(x=2 * hx, y=2 * hy, z=1.0), color=grey)]}
        entities.append(SceneEntity(timestamp=ts(ns), frame_id=WORLD, id=f"obstacle-{i}", metadata=[], **kw))
    return SceneUpdate(deletions=[], entities=entities)


def robots_scene(sc: Scenario, estimates: dict[int, State], ns: int) -> SceneUpdate:
    """Each robot's body (a cylinder, a heading arrow, its id) locked to its true frame ``robot_<id>``, and a
    disc of radius sqrt(trace P) locked to its estimate's frame: how far it believes it may be off. The
    frames move with ``/tf`` and ``/tf_estimate``, so this scene is sent now and then, not every step."""
    entities = []
    for r in sc.robots:
        entities.append(SceneEntity(
            timestamp=ts(ns), frame_id=frame(r.id), id=f"robot-{r.id}", frame_locked=True, metadata=[],
            cylinders=[CylinderPrimitive(pose=pose(0.0, 0.0, 0.0, 0.15), size=Vector3(x=2 * r.radius, y=2 * r.radius, z=0.3),
                                         bottom_scale=1.0, top_scale=1.0, color=_BODY)],
            arrows=[ArrowPrimitive(pose=pose(0.0, 0.0, 0.0, 0.35), shaft_length=r.radius, shaft_diameter=0.08,
                                   head_length=0.25, head_diameter=0.2, color=_WHITE)],
            texts=[TextPrimitive(pose=pose(0.0, 0.0, 0.0, 0.8), billboard=True, font_size=14.0, scale_invariant=True,
                                 color=_WHITE, text=str(r.id))]))
        est = estimates.get(r.id)
        if est is not None:
            sigma = max(math.sqrt(max(est.cov_trace or 0.0, 0.0)), 0.05)
            entities.append(SceneEntity(
                timestamp=ts(ns), frame_id=frame(r.id, estimate=True), id=f"estimate-{r.id}", frame_locked=True, metadata=[],
                cylinders=[CylinderPrimitive(pose=pose(0.0, 0.0, 0.0, 0.02), size=Vector3(x=2 * sigma, y=2 * sigma, z=0.04),
                                             bottom_scale=1.0, top_scale=1.0, color=_ESTIMATE)]))
    return SceneUpdate(deletions=[], entities=entities)


def slot_targets(sc: Scenario, m: Truth, dead: set[int]) -> tuple[int | None, dict[int, tuple[float, float]]]:
    """(leader, follower -> its slot's world position): eq. (3) on the true leader position, with the schedule
    and the failover rule (FormationConfig.resolve) as the agents apply them."""
    f = sc.formation
    if f is None:
        return None, {}
    leader, slots = f.resolve(m.t, dead)
    if leader is None or leader not in m.ids:
        return None, {}
    li = m.ids.index(leader)
    return leader, {rid: slot_position((m.x[li], m.y[li]), s) for rid, s in slots.items()}


def slots_scene(sc: Scenario, targets: dict[int, tuple[float, float]], ns: int) -> SceneUpdate:
    """The followers' slots now: one entity, a flat ring per slot (its id in the entity's metadata, in order)."""
    rings = [CylinderPrimitive(pose=Pose(position=Vector3(x=x, y=y, z=0.01), orientation=_IDENTITY),
                               size=Vector3(x=2 * sc.robot(rid).radius, y=2 * sc.robot(rid).radius, z=0.02),
                               bottom_scale=1.0, top_scale=1.0, color=_SLOT) for rid, (x, y) in targets.items()]
    entity = SceneEntity(timestamp=ts(ns), frame_id=WORLD, id="slots", cylinders=rings,
                         metadata=[KeyValuePair(key="robots", value=",".join(str(r) for r in targets))])
    return _replace_all(ns, [entity])


def metrics(sc: Scenario, m: Truth, leader: int | None, targets: dict[int, tuple[float, float]]) -> dict:
    """Formation error (each follower to its slot) and the closest robot pair and obstacle, from truth
    (as the report computes them: centre distances, obstacle surfaces)."""
    x, y = np.asarray(m.x), np.asarray(m.y)
    errors = {str(rid): math.hypot(x[m.ids.index(rid)] - tx, y[m.ids.index(rid)] - ty)
              for rid, (tx, ty) in targets.items() if rid in m.ids}
    err = np.array(list(errors.values()))
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :]) + np.diag(np.full(len(x), np.inf))
    out = {"step": m.step, "t": m.t, "errors": errors, "leader": -1 if leader is None else leader,
           "formation_error_rms": float(np.sqrt(np.mean(err ** 2))) if err.size else 0.0,
           "formation_error_max": float(err.max()) if err.size else 0.0}
    if len(x) > 1:
        out["min_robot_distance"] = float(d.min())
    if sc.obstacles:
        out["min_obstacle_distance"] = float(distance_to_obstacles(x, y, sc.obstacles).min())
    return out


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
