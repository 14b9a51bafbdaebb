"""The fleet's own Foxglove builders, from the world's ground truth (true poses, slots on the true leader,
metrics) and the bodies on their true frames; the rest (topics, schemas, scans, estimates, obstacles, links)
is shared with a robot's own view and comes from :mod:`stack.viz.messages`, re-exported here.

Pure functions, no I/O: :mod:`.record` calls them on its writer thread, :mod:`.replay` reads the topics back.
"""

from __future__ import annotations

import math

import numpy as np
from foxglove.messages import (ArrowPrimitive, CylinderPrimitive, FrameTransform, FrameTransforms, SceneEntity, SceneUpdate,
                               TextPrimitive, Vector3)

from ..comm.messages import State, Truth
from ..scenario import Scenario, slot_position
from ..sim_bridge.geometry import distance_to_obstacles
from ..viz.messages import (_BODY, _ESTIMATE, _REAL, _STALE, _WHITE, JSON_SCHEMAS, LINK_COLORS, NO_RETURN, ROBOT_TOPICS,  # noqa: F401
                            TOPICS, WORLD, diag_doc, estimate_frame, estimate_transform, frame, laser_scan, links_scene,
                            obstacles_scene, pose, pose_in_world, quat, robot_topic, slots_scene, ts)


def truth_transforms(m: Truth, ns: int) -> FrameTransforms:
    """world -> robot_<id>: every robot's true pose at this step."""
    return FrameTransforms(transforms=[
        FrameTransform(timestamp=ts(ns), parent_frame_id=WORLD, child_frame_id=frame(rid),
                       translation=Vector3(x=x, y=y, z=0.0), rotation=quat(yaw))
        for rid, x, y, yaw in zip(m.ids, m.x, m.y, m.yaw)])


def robots_scene(sc: Scenario, estimates: dict[int, State], ns: int, stale: set[int] | frozenset[int] = frozenset()
                 ) -> SceneUpdate:
    """Each robot's body (a cylinder, a heading arrow, its id) locked to its true frame ``robot_<id>``, and a
    disc of radius sqrt(trace P) locked to its estimate's frame: how far it believes it may be off. The
    frames move with ``/tf`` and ``/tf_estimate``, so this scene is sent now and then, not every step. A real
    robot (``embodiment: real``) is green, labelled ``<id> real``; grey and ``<id> stale`` while its pose is."""
    entities = []
    for r in sc.robots:
        body, label = _BODY, str(r.id)
        if r.embodiment == "real":
            body, label = (_STALE, f"{r.id} stale") if r.id in stale else (_REAL, f"{r.id} real")
        entities.append(SceneEntity(
            timestamp=ts(ns), frame_id=frame(r.id), id=f"robot-{r.id}", frame_locked=True, metadata=[],
            cylinders=[CylinderPrimitive(pose=pose(0.0, 0.0, 0.0, 0.15), size=Vector3(x=2 * r.radius, y=2 * r.radius, z=0.3),
                                         bottom_scale=1.0, top_scale=1.0, color=body)],
            arrows=[ArrowPrimitive(pose=pose(0.0, 0.0, 0.0, 0.35), shaft_length=r.radius, shaft_diameter=0.08,
                                   head_length=0.25, head_diameter=0.2, color=_WHITE)],
            texts=[TextPrimitive(pose=pose(0.0, 0.0, 0.0, 0.8), billboard=True, font_size=14.0, scale_invariant=True,
                                 color=_WHITE, text=label)]))
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


def metrics(sc: Scenario, m: Truth, leader: int | None, targets: dict[int, tuple[float, float]]) -> dict:
    """Formation error (each follower to its slot) and the closest robot pair and obstacle, from truth
    (as the report computes them: centre distances, obstacle surfaces)."""
    x, y = np.asarray(m.x), np.asarray(m.y)
    index = {rid: i for i, rid in enumerate(m.ids)}
    errors = {str(rid): math.hypot(m.x[index[rid]] - tx, m.y[index[rid]] - ty)
              for rid, (tx, ty) in targets.items() if rid in index}
    err = np.array(list(errors.values()))
    out = {"step": m.step, "t": m.t, "errors": errors, "leader": -1 if leader is None else leader,
           "formation_error_rms": float(np.sqrt(np.mean(err ** 2))) if err.size else 0.0,
           "formation_error_max": float(err.max()) if err.size else 0.0}
    if len(x) > 1:
        d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
        np.fill_diagonal(d, np.inf)
        out["min_robot_distance"] = float(d.min())
    if sc.obstacles:
        out["min_obstacle_distance"] = _obstacles(sc).min_distance(x, y)
    return out


class _Obstacles:
    """The scenario's obstacles for :func:`metrics`: the cylinders as arrays (one broadcast, not a loop over
    them), the boxes and walls as :func:`~stack.sim_bridge.geometry.distance_to_obstacles` has them; the same
    floats (elementwise the same operations, and a minimum is exact)."""

    def __init__(self, obstacles):
        cyl = [o for o in obstacles if o.type == "cylinder"]
        self.cx, self.cy, self.cr = (np.array([getattr(o, a) for o in cyl], float) for a in ("x", "y", "radius"))
        self.others = [o for o in obstacles if o.type != "cylinder"]

    def min_distance(self, x: np.ndarray, y: np.ndarray) -> float:
        best = math.inf
        if self.cx.size:
            d = np.hypot(x[:, None] - self.cx[None, :], y[:, None] - self.cy[None, :]) - self.cr[None, :]
            best = float(np.maximum(d, 0.0).min())
        if self.others:
            best = min(best, float(distance_to_obstacles(x, y, self.others).min()))
        return best


_OBSTACLES: dict[int, tuple[object, _Obstacles]] = {}


def _obstacles(sc: Scenario) -> _Obstacles:
    hit = _OBSTACLES.get(id(sc.obstacles))
    if hit is None or hit[0] is not sc.obstacles:
        hit = _OBSTACLES[id(sc.obstacles)] = (sc.obstacles, _Obstacles(sc.obstacles))
    return hit[1]
