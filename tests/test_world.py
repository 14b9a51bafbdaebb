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

GRAZE = 0.01  # [m] every shape grown and shrunk by this for the two-sided bounds (beams that graze an edge)


def _world(**over):
    return World(parse_scenario(scenario_dict(**over), "w.yaml"))


def _ray_circle(ox, oy, ux, uy, cx, cy, r, t_min):
    """Distance along the unit ray (ox, oy) + t (ux, uy), t >= t_min, to the circle's boundary; inf if it misses."""
    fx, fy = ox - cx, oy - cy
    b = fx * ux + fy * uy
    disc = b * b - (fx * fx + fy * fy - r * r)
    if disc < 0:
        return math.inf
    for t in (-b - math.sqrt(disc), -b + math.sqrt(disc)):
        if t >= t_min:
            return t
    return math.inf


def _ray_box(ox, oy, ux, uy, box, t_min):
    """Distance to the boundary of the rotated rectangle (cx, cy, hx, hy, yaw) by the slab method; inf if it misses."""
    cx, cy, hx, hy, yaw = box
    c, s = math.cos(yaw), math.sin(yaw)
    px, py = c * (ox - cx) + s * (oy - cy), -s * (ox - cx) + c * (oy - cy)
    dx, dy = c * ux + s * uy, -s * ux + c * uy
    lo, hi = -math.inf, math.inf
    for p_, d_, h in ((px, dx, hx), (py, dy, hy)):
        if abs(d_) < 1e-12:
            if abs(p_) > h:
                return math.inf
            continue
        t1, t2 = sorted(((-h - p_) / d_, (h - p_) / d_))
        lo, hi = max(lo, t1), min(hi, t2)
    if lo > hi:
        return math.inf
    for t in (lo, hi):
        if t >= t_min:
            return t
    return math.inf


def expected_ranges(w: World, rid: int, grow: float, robots: bool = True) -> np.ndarray:
    """Each beam's range of robot ``rid`` cast analytically in 2D against the scenario's obstacles (and the
    other robots' discs), every shape grown by ``grow`` (negative: shrunk). Rays start at the body's edge."""
    i = w.index[rid]
    lid = w.sc.robots[i].lidar
    x, y, r0 = w.x[i], w.y[i], w.ray_offsets[i]
    discs = [(o.x, o.y, o.radius) for o in w.sc.obstacles if o.type == "cylinder"]
    if robots:
        discs += [(w.x[j], w.y[j], w.radii[j]) for j in range(len(w.x)) if j != i]
    boxes = [o.as_box() for o in w.sc.obstacles if o.type != "cylinder"]
    out = []
    for a in w.yaw[i] + w.beam_angles[i]:
        ux, uy = math.cos(a), math.sin(a)
        t = min([_ray_circle(x, y, ux, uy, cx, cy, rr + grow, r0) for cx, cy, rr in discs]
                + [_ray_box(x, y, ux, uy, (cx, cy, hx + grow, hy + grow, yw), r0) for cx, cy, hx, hy, yw in boxes]
                + [math.inf])
        out.append(min(t, lid.range))
    return np.array(out)


def assert_matches_geometry(w: World, rid: int, ranges: np.ndarray) -> None:
    """Two-sided: every beam reads between the range to the grown shapes and the range to the shrunk ones."""
    lo, hi = expected_ranges(w, rid, GRAZE), expected_ranges(w, rid, -GRAZE)
    bad = np.nonzero((ranges < lo - 1e-6) | (ranges > hi + 1e-6))[0]
    assert bad.size == 0, [(int(k), float(lo[k]), float(ranges[k]), float(hi[k])) for k in bad[:5]]


def test_analytic_ray_cast_on_hand_cases():
    """The oracle itself: a circle straight ahead, a box corner-on, a miss, a ray starting inside a shape."""
    assert _ray_circle(0, 0, 1, 0, 3, 0, 0.5, 0.0) == pytest.approx(2.5)
    assert _ray_circle(0, 0, 0, 1, 3, 0, 0.5, 0.0) == math.inf
    assert _ray_circle(0, 0, 1, 0, 0, 0, 1.0, 0.5) == pytest.approx(1.0)  # from inside: the far side
    s = math.sqrt(0.5)
    assert _ray_box(0, 0, 1, 0, (3, 0, s, s, math.pi / 4), 0.0) == pytest.approx(2.0)  # a diamond's left corner at x = 2
    assert _ray_box(0, 0, 0, 1, (3, 0, 1, 1, 0.0), 0.0) == math.inf
    assert _ray_box(0, 0, 1, 0, (0, 0, 2, 1, 0.3), 0.0) == pytest.approx(2 / math.cos(0.3))  # from inside, long side


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
    assert_matches_geometry(w, 0, r)   # and every other beam


def test_other_robots_block_rays():
    w = _world()
    r1 = w.lidar([1])[1]  # robot 1 at (-1, 3.5) facing -30 deg: robot 0 at 3.6 m, robot 2 at 5.0 m, the wall 4.4 m
    assert_matches_geometry(w, 1, r1)
    no_robots = expected_ranges(w, 1, -GRAZE, robots=False)
    blocked = np.nonzero(r1 < no_robots - 0.1)[0]  # beams that only a robot's body can have stopped
    assert blocked.size >= 10, blocked
    # the beam nearest the direction of robot 0's centre, by hand: it meets the disc of radius 0.5 at
    # d0 cos(delta) - sqrt(0.25 - (d0 sin(delta))^2), delta its angle off the centre (half a beam step at most)
    ang = w.yaw[1] + w.beam_angles[1]
    to0 = math.atan2(w.y[0] - w.y[1], w.x[0] - w.x[1])
    off = (ang - to0 + math.pi) % (2 * math.pi) - math.pi
    k = int(np.argmin(np.abs(off)))
    d0 = math.hypot(w.x[0] - w.x[1], w.y[0] - w.y[1])
    hit = d0 * math.cos(off[k]) - math.sqrt(0.25 - (d0 * math.sin(off[k])) ** 2)
    assert abs(r1[k] - hit) < 0.01 and hit < no_robots[k] - 0.5, (r1[k], hit, no_robots[k])


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


def test_lidar_agrees_with_exact_geometry_on_a_random_field():
    """Random poses among the obstacles (others far away): every beam between the grown and the shrunk
    shapes' analytic ranges, and the nearest reading never below the exact distance to the nearest surface."""
    sc = load_scenario(SCENARIOS / "four-robot-obstacles.yaml")
    for r in sc.robots:
        object.__setattr__(r, "lidar", dataclasses.replace(r.lidar, noise_std=0.0))
    w = World(sc)
    rng = np.random.default_rng(2)
    lid = w.sc.robots[0].lidar
    hits = poses = 0
    while poses < 50:
        x, y = rng.uniform(5, 30), rng.uniform(-7, 7)
        d = distance_to_obstacles(np.array([x]), np.array([y]), sc.obstacles)[0]
        if d <= w.ray_offsets[0] + GRAZE:
            continue  # the robot's body would overlap an obstacle: not a pose it can be in (rays would start inside)
        poses += 1
        w.x[:] = [x, 0, 0, 0]
        w.y[:] = [y, 40, 80, 120]  # others far away: obstacles only
        w.yaw[0] = rng.uniform(-math.pi, math.pi)
        w._sync_bodies()
        r = w.lidar([0])[0]
        assert_matches_geometry(w, 0, r)
        assert r.min() >= min(d, lid.range) - GRAZE  # never nearer than the nearest surface
        hits += int((r < lid.range).sum())
    assert hits > 500, hits  # the field is dense enough that the comparison covers many hits


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


def test_the_truth_log_spills_whole_chunks_and_saves_what_it_held(tmp_path):
    """``TruthRows``: a run longer than a chunk keeps at most a chunk in memory; truth.npz is every row, in order."""
    import numpy as np

    from stack.sim_bridge.truthlog import KEYS, TruthRows

    rows = TruthRows(tmp_path, chunk=4)
    for k in range(10):
        rows["t"].append(0.1 * k)
        for key in KEYS[1:]:
            rows[key].append(np.full(3, float(k)) if key != "alive" else np.ones(3, bool))
        rows.step_done()
        assert len(rows["t"]) < 4
    assert len(rows.spilled) == 2
    rows["t"].append(1.0)
    rows.save(tmp_path / "truth.npz", ids=np.arange(3))
    z = np.load(tmp_path / "truth.npz")
    assert z["t"].shape == (11,) and z["x"].shape == (10, 3) and list(z["x"][:, 0]) == [float(k) for k in range(10)]
    assert list(z["ids"]) == [0, 1, 2] and not list(tmp_path.glob(".truth-*"))
