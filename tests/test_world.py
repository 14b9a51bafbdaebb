"""The pybullet world: lidar against exact geometry, beam culling exact, diff drive with acceleration limits."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from conftest import SCENARIOS, scenario_dict
from stack.scenario import load_scenario, parse_scenario
from stack.sim_bridge.geometry import distance_to_obstacles
from stack.sim_bridge.world import World


def _world(**over):
    return World(parse_scenario(scenario_dict(**over), "w.yaml"))


def test_lidar_hits_match_geometry():
    w = _world(world={"obstacles": [{"type": "cylinder", "x": 3.0, "y": 0.0, "radius": 0.5},
                                    {"type": "wall", "from": [-5, 2], "to": [5, 2], "thickness": 0.2}]},
               robots=[{"id": 0, "role": "leader", "pose": [0, 0, 0]}], formation={"leader": 0, "goal": [9, 0], "slots": {}})
    r = w.lidar()[0]
    ang = w.beam_angles[0]
    assert len(r) == 180 and math.isclose(ang[0], -math.pi / 2) and math.isclose(ang[-1], math.pi / 2)
    ahead = np.argmin(np.abs(ang))
    assert abs(r[ahead] - 2.5) < 0.01  # cylinder surface
    assert abs(r[-1] - 1.9) < 0.01     # wall at y = 2 - 0.1, straight left
    assert r[0] == 5.0                 # nothing to the right: max range


def test_other_robots_block_rays():
    w = _world()
    r1 = w.lidar([1])[1]  # robot 1 at (-1, 3.5) facing -30 deg
    assert r1.min() < 5.0


@pytest.mark.parametrize("name", ["four-robot-obstacles", "six-robot"])
def test_beam_culling_is_exact(name):
    sc = load_scenario(SCENARIOS / f"{name}.yaml")
    for r in sc.robots:
        object.__setattr__(r, "lidar", dataclasses.replace(r.lidar, noise_std=0.0))
    w = World(sc)
    rng = np.random.default_rng(5)
    for _ in range(300):
        n = len(w.x)
        w.x[:], w.y[:], w.yaw[:] = rng.uniform(-2, 38, n), rng.uniform(-8, 8, n), rng.uniform(-math.pi, math.pi, n)
        w._sync_bodies()
        w.cull = True
        a = w.lidar()
        w.cull = False
        b = w.lidar()
        for k in a:
            assert np.array_equal(a[k], b[k])


def test_lidar_agrees_with_exact_distance_on_a_random_field():
    sc = load_scenario(SCENARIOS / "four-robot-obstacles.yaml")
    for r in sc.robots:
        object.__setattr__(r, "lidar", dataclasses.replace(r.lidar, noise_std=0.0))
    w = World(sc)
    rng = np.random.default_rng(2)
    for _ in range(50):
        w.x[:] = rng.uniform(5, 30, 4)
        w.y[:] = rng.uniform(-7, 7, 4) + np.array([0, 40, 80, 120])  # others far away: obstacles only
        w._sync_bodies()
        d = distance_to_obstacles(w.x[:1], w.y[:1], sc.obstacles)[0]
        r = w.lidar([0])[0]
        if d < 4.0 and d > 0.6:
            # the nearest surface is at d; beams only see the forward half, so never closer than d
            assert r.min() >= d - 0.02


def test_diff_drive_acceleration_limit_and_arc():
    w = _world()
    b = w.sc.robots[0].base
    w.step({0: (1.0, 0.0)}, 0.1)
    assert math.isclose(w.v[0], b.wheel_accel * 0.1 * b.wheel_radius)  # one step of wheel acceleration
    for _ in range(50):
        w.step({0: (1.0, 0.0)}, 0.1)
    assert math.isclose(w.v[0], 1.0)
    for _ in range(10):  # settle on the arc
        w.step({0: (0.5, 0.5)}, 0.1)
    x0, y0, th0 = w.x[0], w.y[0], w.yaw[0]
    for _ in range(40):
        w.step({0: (0.5, 0.5)}, 0.1)
    # steady arc of radius v / w = 1 m: the robot stays on a circle
    assert abs(w.v[0] - 0.5) < 1e-9 and abs(w.w[0] - 0.5) < 1e-9
    cx, cy = x0 - math.sin(th0), y0 + math.cos(th0)
    assert abs(math.hypot(w.x[0] - cx, w.y[0] - cy) - 1.0) < 1e-9
