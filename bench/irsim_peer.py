"""IR-SIM as a single-process peer simulator for the fleet benchmark.

Builds the IR-SIM (``pip install ir-sim``, import ``irsim``) world of one of our scenarios and
steps it headless, doing the world work our own simulator does each step: N differential-drive
robots of the scenario's radius and velocity limits, each with a 2D lidar of the scenario's
beams / field of view / range (180 beams, 180 deg, 5 m in our scenarios) cast against the same
static obstacles and the other robots, at the scenario's dt (0.1 s).

Each robot is driven toward its own goal by IR-SIM's built-in ``dash`` behaviour for ``diff``
kinematics: the formation goal for the leader, the formation goal offset by the follower's slot
(``stack.scenario.slot_position``), or the robot's own ``goal``. The world runs with
``collision_mode: unobstructed``: IR-SIM still tests collisions every step but no robot stops.
The environment is made with ``headless=True``: no figure, window, keyboard/mouse hook,
plot or animation file. Only the stepping loop is timed, not the world construction.

    python bench/irsim_peer.py scenarios/six-robot.yaml --steps 300
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")  # before anything imports matplotlib
ROOT = str(Path(__file__).resolve().parents[1])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)  # repo root, for `stack`

import matplotlib  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

with contextlib.redirect_stdout(io.StringIO()):  # its import tries TkAgg/Qt5Agg and prints why not
    import irsim  # noqa: E402
matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402

from stack.scenario import Scenario, load_scenario, slot_position  # noqa: E402

PAD = 6.0  # [m] world margin around robots, goals and obstacles (> lidar range)


def _goal(sc: Scenario, robot) -> tuple[float, float]:
    """The leader's goal, a follower's slot at the formation goal, or the robot's own goal."""
    f = sc.formation
    if f is not None and robot.id == f.leader:
        return f.goal
    if f is not None and robot.id in f.slots:
        return slot_position(f.goal, f.slots[robot.id])
    return robot.goal if robot.goal is not None else robot.pose[:2]


def _obstacle(o) -> dict:
    """One of our obstacles as an IR-SIM static obstacle: a circle or a yawed rectangle."""
    if o.type == "cylinder":
        return {"kinematics": {"name": "static"}, "shape": {"name": "circle", "radius": o.radius},
                "state": [o.x, o.y, 0.0]}
    cx, cy, hx, hy, yaw = o.as_box()
    return {"kinematics": {"name": "static"}, "shape": {"name": "rectangle", "length": 2 * hx, "width": 2 * hy},
            "state": [cx, cy, yaw]}


def _world_bounds(sc: Scenario) -> tuple[float, float, float, float]:
    pts = [r.pose[:2] for r in sc.robots] + [_goal(sc, r) for r in sc.robots]
    for o in sc.obstacles:
        if o.type == "cylinder":
            pts += [(o.x - o.radius, o.y - o.radius), (o.x + o.radius, o.y + o.radius)]
        else:
            cx, cy, hx, hy, _ = o.as_box()
            ext = math.hypot(hx, hy)  # bounding circle of the rotated box
            pts += [(cx - ext, cy - ext), (cx + ext, cy + ext)]
    xy = np.asarray(pts, dtype=float)
    lo, hi = xy.min(axis=0) - PAD, xy.max(axis=0) + PAD
    return float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])


def world_config(sc: Scenario) -> dict:
    """The IR-SIM world YAML (as a dict) of scenario ``sc``."""
    x0, y0, width, height = _world_bounds(sc)
    robots = []
    for r in sc.robots:
        lidar = {"name": "lidar2d", "number": r.lidar.beams, "angle_range": r.lidar.fov,
                 "range_min": 0.0, "range_max": r.lidar.range}
        if r.lidar.noise_std > 0:
            lidar |= {"noise": True, "std": r.lidar.noise_std}
        robots.append({
            "name": f"robot_{r.id}",
            "kinematics": {"name": "diff"},
            "shape": {"name": "circle", "radius": r.radius},
            "state": list(r.pose),
            "goal": [*_goal(sc, r), 0.0],
            "goal_threshold": sc.success.goal_tolerance,
            "vel_min": [-r.v_max, -r.w_max],
            "vel_max": [r.v_max, r.w_max],
            "behavior": {"name": "dash"},
            "sensors": [lidar],
        })
    return {
        "world": {"width": width, "height": height, "offset": [x0, y0],
                  "step_time": sc.dt, "control_mode": "auto", "collision_mode": "unobstructed"},
        "robot": robots,
        "obstacle": [_obstacle(o) for o in sc.obstacles],
    }


def run_irsim(scenario_path: str, steps: int, seed: int = 0) -> dict:
    """Build the IR-SIM world of our scenario and step it `steps` times headless.
    Returns {'robots': N, 'steps': steps, 'wall_s': float, 'steps_per_s': float,
             'lidar_beams': int, 'irsim_version': str}."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    sc = load_scenario(scenario_path)
    with tempfile.TemporaryDirectory(prefix="irsim_peer_") as tmp:
        world_file = Path(tmp) / f"{sc.name}.yaml"
        world_file.write_text(yaml.safe_dump(world_config(sc), sort_keys=False))
        env = irsim.make(str(world_file), headless=True, display=False, save_ani=False,
                         log_level="ERROR", seed=seed)
    try:
        robots = env.robot_list
        if len(robots) != len(sc.robots) or not env.headless or plt.get_fignums():
            raise RuntimeError("IR-SIM world does not match the scenario or is not headless")
        start = np.array([r.state[:2, 0] for r in robots])

        t0 = time.perf_counter()
        for _ in range(steps):
            env.step()
        wall = time.perf_counter() - t0

        for r, cfg in zip(robots, sc.robots, strict=True):  # a full scan per robot, last step
            n = len(r.get_lidar_scan()["ranges"])
            if n != cfg.lidar.beams:
                raise RuntimeError(f"{r.name}: lidar gave {n} ranges, expected {cfg.lidar.beams}")
        moved = np.linalg.norm(np.array([r.state[:2, 0] for r in robots]) - start, axis=1)
        far = np.linalg.norm(np.array([r.goal[:2, 0] for r in robots]) - start, axis=1) > sc.success.goal_tolerance
        if np.any(moved[far] < 1e-3):
            raise RuntimeError(f"robots with a distant goal did not move: {np.flatnonzero(far & (moved < 1e-3))}")
    finally:
        env.end(ending_time=0.0)
    return {"robots": len(robots), "steps": steps, "wall_s": wall, "steps_per_s": steps / wall,
            "lidar_beams": sc.robots[0].lidar.beams, "irsim_version": irsim.__version__}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", help="our scenario YAML")
    ap.add_argument("--steps", type=int, default=300, help="number of steps to time (default 300)")
    ap.add_argument("--seed", type=int, default=0, help="IR-SIM random seed (lidar noise)")
    args = ap.parse_args(argv)
    print(json.dumps(run_irsim(args.scenario, args.steps, args.seed), indent=2))


if __name__ == "__main__":
    main()
