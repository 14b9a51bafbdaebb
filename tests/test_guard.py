"""The collision guard under every policy (stack/agents/guard.py): the forward speed the robot can stop from.

In process: the guard's geometry on hand-made scans, then a step pipeline driving a robot that its policy
would put into a wall, on the exact unicycle arc (no Zenoh, no world)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import scenario_dict

from stack.agents.guard import CollisionGuard, GuardConfig
from stack.agents.step import OdomSample, StepConfig, StepInputs, StepPipeline
from stack.comm.messages import Scan
from stack.models.kinematics import arc_step
from stack.scenario import parse_scenario

FOV, BEAMS, RANGE = math.pi, 181, 5.0


def wall_scan(x_wall: float, beams: int = BEAMS) -> np.ndarray:
    """Ranges from the robot's centre to a wall across its path at x = x_wall (robot frame)."""
    ang = np.linspace(-FOV / 2, FOV / 2, beams)
    with np.errstate(divide="ignore"):
        r = np.where(np.cos(ang) > 1e-9, x_wall / np.cos(ang), np.inf)
    return np.minimum(r, RANGE)


def test_free_distance_to_a_wall_and_a_post_beside_the_path():
    g = CollisionGuard(0.5, FOV, BEAMS, RANGE, GuardConfig(margin=0.1))
    assert g.free_distance(wall_scan(2.0)) == pytest.approx(1.4)  # the grown disc's front is 0.6 m ahead
    assert g.free_distance(np.full(BEAMS, RANGE)) == math.inf  # nothing seen
    post = np.full(BEAMS, RANGE)
    post[90 + 40] = 1.0  # 40 deg left, 1 m away: (0.77, 0.64), outside the 0.6 m corridor
    assert g.free_distance(post) == math.inf
    post[90 + 30] = 1.0  # 30 deg left: (0.87, 0.5), inside it
    assert g.free_distance(post) == pytest.approx(0.866 - math.sqrt(0.36 - 0.25), abs=1e-3)
    assert g.free_distance(np.full(BEAMS - 1, 1.0)) == math.inf  # another beam layout: judges nothing


def test_the_speed_it_allows_stops_in_time_and_it_never_limits_turning_or_reversing():
    cfg = GuardConfig(margin=0.1, decel=1.0, lag_s=0.1)
    g = CollisionGuard(0.5, FOV, BEAMS, RANGE, cfg)
    for d in (0.05, 0.3, 1.0, 3.0):
        v = g.stoppable_speed(d)
        assert v * cfg.lag_s + v * v / (2 * cfg.decel) == pytest.approx(d)  # lag, then braking: exactly d
    assert g.limit(0.8, wall_scan(0.65)) == pytest.approx(g.stoppable_speed(0.05))
    assert g.limit(0.8, wall_scan(0.55)) == 0.0  # already inside the margin: no forward motion
    assert g.limit(-0.3, wall_scan(0.55)) == -0.3 and g.limit(0.0, wall_scan(0.55)) == 0.0
    assert g.limit(0.8, wall_scan(4.5)) == 0.8 and g.capped == 2
    off = CollisionGuard(0.5, FOV, BEAMS, RANGE, GuardConfig(enabled=False))
    assert off.limit(0.8, wall_scan(0.55)) == 0.8 and off.capped == 0
    with pytest.raises(ValueError, match="decel"):
        GuardConfig(decel=0.0)


def test_a_base_still_rolling_with_something_inside_the_margin_must_brake_straight():
    g = CollisionGuard(0.5, FOV, BEAMS, RANGE, GuardConfig(margin=0.1))
    assert g.must_brake(0.1, wall_scan(0.58), w=1.0)  # inside the margin, still rolling: both rates zero
    assert g.must_brake(0.1, wall_scan(0.58), w=0.0)
    assert not g.must_brake(0.1, wall_scan(1.0), w=-1.0)  # 0.4 m free
    assert not g.must_brake(0.01, wall_scan(0.58), w=1.0)  # stopped (odometry noise): turning in place is free
    assert not g.must_brake(-0.2, wall_scan(0.58))  # reversing away
    assert g.brakes == 2
    assert not g.must_brake(g.stoppable_speed(0.3) + 0.5, wall_scan(0.9))  # outside the margin the caps keep it
    off = CollisionGuard(0.5, FOV, BEAMS, RANGE, GuardConfig(enabled=False))
    assert not off.must_brake(0.1, wall_scan(0.58)) and off.brakes == 0


GRAZE_OBSTACLES = [
    {"type": "wall", "from": [-5.769, 7.0], "to": [41.957, 7.0], "thickness": 0.2},
    {"type": "wall", "from": [-5.769, -7.0], "to": [41.957, -7.0], "thickness": 0.2},
    {"type": "wall", "from": [20.297, -7.0], "to": [20.297, -3.819], "thickness": 0.3},
    {"type": "wall", "from": [20.297, 3.664], "to": [20.297, 7.0], "thickness": 0.3},
    {"type": "cylinder", "x": 8.991, "y": -2.024, "radius": 0.51},
    {"type": "box", "x": 15.203, "y": -2.297, "size_x": 1.16, "size_y": 0.898, "yaw_deg": 140.874},
    {"type": "cylinder", "x": 12.387, "y": 2.062, "radius": 0.636},
    {"type": "cylinder", "x": 24.087, "y": 0.505, "radius": 0.528},
]
"""The obstacles of held-out course 1,000,052 (``medium``; a spent seed: its table is reported) around the box an
``aina`` leader grazed, the course's own numbers."""


@pytest.mark.fleet
def test_the_graze_beside_a_box_rebuilt_from_its_course_keeps_the_margin(tmp_path):
    """The ``aina`` leader of course 1,000,052, alone, started where it was 4 s before it grazed the box ahead on
    its right: aina chatters between (0.3, +1) and (0, -1) there, and a base whose wheels ramp at a bounded rate does
    not stop under that; it crept on at 0.1 m/s with its commanded ``v`` zero. Without the brake (the guard capping
    ``v`` alone) its body came within 7.3 cm of the box here, inside the 10 cm margin (on the whole course 0.8 cm
    into it); with it the margin holds."""
    from conftest import run_fleet, write_scenario

    d = scenario_dict(duration=20.0)
    d["world"] = {"obstacles": GRAZE_OBSTACLES}
    d["robot"] = dict(d["robot"], lidar={"beams": 180, "fov_deg": 180, "range": 5.0, "noise_std": 0.01})
    d["formation"] = {"leader": 0, "goal": [36.957, 0.0], "slots": {}}
    d["robots"] = [{"id": 0, "role": "leader", "pose": [13.0, -2.05, 3.0], "policy": "aina"}]
    d["success"] = {"goal_tolerance": 0.5, "max_time": 20.0, "no_collisions": True}
    proc, rep = run_fleet(write_scenario(tmp_path / "graze.yaml", d), tmp_path / "out", "--no-plots", "--no-record")
    assert rep is not None and rep["crashed"] == [], proc.stdout + proc.stderr
    assert rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    assert rep["robots"]["0"]["guard_brakes"] > 0  # the case is met: it rolled where it could not stop
    assert rep["min_obstacle_distance_m"] >= 0.5 + 0.1 - 0.01, rep["min_obstacle_distance_m"]  # radius + margin


def test_on_an_arc_it_judges_the_ring_the_turning_disc_sweeps():
    g = CollisionGuard(0.5, FOV, BEAMS, RANGE, GuardConfig(margin=0.1))
    post = np.full(BEAMS, RANGE)
    post[90 + 60] = 1.2  # 60 deg left, 1.2 m: (0.6, 1.04), beside the straight corridor
    assert g.free_distance(post) == math.inf
    # turning left on rho = 1 m (centre (0, 1)): the post is 0.4 m inside the circle, inside the 0.6 m ring; the
    # robot reaches its bearing after turning pi/2 + atan2(0.04, 0.6) about the centre, and its centre comes within
    # 0.6 m of the post Delta before that (the triangle centre-post-robot: sides dc, 1 and 0.6)
    dc = math.hypot(0.6, 1.04 - 1.0)
    expect = math.pi / 2 + math.atan2(0.04, 0.6) - math.acos((dc ** 2 + 1.0 - 0.36) / (2 * dc))
    assert g.free_distance(post, 1.0) == pytest.approx(expect, abs=2e-3)
    # a point already within the margin, that the arc passes nearer still (the chord estimate said 0.30 m free)
    side = np.full(BEAMS, RANGE)
    side[90 - 80] = 0.497  # 80 deg right, 0.497 m: (0.086, -0.489)
    assert g.free_distance(side, -2.0) < 0.0  # turning right on rho = 0.5 m toward it: held
    assert g.limit(0.3, side, -0.6) == 0.0
    assert g.free_distance(post, -1.0) == math.inf  # turning right, away from it
    ahead = np.full(BEAMS, RANGE)
    ahead[90] = 2.0
    assert g.free_distance(ahead, 1e-4) == pytest.approx(1.4)  # a 10 km arc is the straight corridor
    assert g.free_distance(ahead, 2e-3) == pytest.approx(1.4, abs=1e-3)  # and a 500 m one nearly so
    soft = CollisionGuard(0.5, FOV, BEAMS, RANGE, GuardConfig(margin=0.1, decel=0.25))  # stops from 0.75 m/s in 1.19 m
    assert soft.limit(0.8, post, 0.0) == 0.8 and soft.limit(0.8, post, -0.8) == 0.8  # straight or away: free
    capped = soft.limit(0.8, post, 0.8)
    assert capped < 0.8 and soft.capped == 1
    # the capped speed at the same w is a tighter arc: it too must stop in time on that arc
    assert capped <= soft.stoppable_speed(soft.free_distance(post, 0.8 / capped)) + 1e-9


def post_scan(x: float, y: float, yaw: float, cx: float, cy: float, rad: float) -> np.ndarray:
    """Ranges from (x, y, yaw) to a round post of radius ``rad`` at (cx, cy) (exact ray-circle hits)."""
    a = yaw + np.linspace(-FOV / 2, FOV / 2, BEAMS)
    ux, uy = np.cos(a), np.sin(a)
    ox, oy = cx - x, cy - y
    b = ux * ox + uy * oy
    disc = b * b - (ox * ox + oy * oy - rad * rad)
    t = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    return np.where((t > 0) & np.isfinite(t), np.minimum(t, RANGE), RANGE)


def test_a_robot_turning_into_a_post_beside_it_stops_short_of_it():
    """The held-out graze: a robot turning with forward speed beside an obstacle (outside the straight corridor
    ahead at every step) swept into it. Driven on the exact unicycle arc, the command always v = 0.8, w = 0.8."""
    cx, cy, rad = 0.6, 1.9, 0.3  # 1.9 m left of the start, 0.6 m ahead: on the 1 m circle the robot drives
    for enabled in (True, False):
        g = CollisionGuard(0.5, FOV, BEAMS, RANGE, GuardConfig(margin=0.1, enabled=enabled))
        x = y = yaw = 0.0
        gap = math.inf
        for _ in range(60):
            v = g.limit(0.8, post_scan(x, y, yaw, cx, cy, rad), 0.8)
            x, y, yaw = arc_step(x, y, yaw, v, 0.8, 0.1)
            gap = min(gap, math.hypot(x - cx, y - cy) - rad - 0.5)
        if enabled:
            assert g.capped > 0 and gap > 0.0  # it never touched
        else:
            assert gap < 0.0  # without the guard the same command runs into the post


def _drive(guard: GuardConfig, steps: int = 120) -> tuple[float, int]:
    """A pid leader with its goal beyond a wall at x = 3 m: how close its centre gets to the wall, and how
    many steps the guard capped. The scan is cast analytically from the true pose each step."""
    d = scenario_dict(duration=20.0)
    d["robots"] = [{"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0]}]
    d["formation"] = {"leader": 0, "goal": [8.0, 0.0], "slots": {}}
    d["robot"]["lidar"] = {"beams": BEAMS, "fov_deg": 180, "range": RANGE, "noise_std": 0.0}
    sc = parse_scenario(d)
    pl = StepPipeline(sc, 0, policy="pid", config=StepConfig(guard=guard))
    x = y = yaw = 0.0
    v = w = 0.0
    closest = math.inf
    for k in range(steps):
        t = k * sc.dt
        ranges = wall_scan(3.0 - x).tolist()
        scan = Scan(id=0, stamp=t, step=k, angle_min=-FOV / 2, angle_increment=FOV / (BEAMS - 1), range_max=RANGE,
                    ranges=ranges)
        odo = OdomSample(t=t, v=v, w=w, pose=(x, y, yaw))
        out = pl.step(StepInputs(step=k, t=t, t_run=t, now=t, odometry=(odo,), scan=scan, scan_t=t))
        v, w = out.v, out.w
        x, y, yaw = arc_step(x, y, yaw, v, w, sc.dt)
        closest = min(closest, 3.0 - x)
    return closest, pl.guard.capped


def test_a_policy_that_would_drive_into_a_wall_stops_short_of_it():
    closest, capped = _drive(GuardConfig(margin=0.1))
    assert capped > 0
    assert 0.5 + 0.1 - 0.02 <= closest <= 0.5 + 0.1 + 0.1  # stopped at the margin, not far before it
    closest_off, capped_off = _drive(GuardConfig(enabled=False))
    assert capped_off == 0 and closest_off < 0.5  # the same pid without the guard drives into the wall


def test_the_way_out_is_the_nearest_heading_whose_corridor_is_free():
    g = CollisionGuard(0.5, FOV, BEAMS, RANGE, GuardConfig(margin=0.1, slide_free=0.3))
    post = post_scan(0.0, 0.0, 0.0, 0.45, -0.75, 0.2)  # ahead right, its edge 0.05 m inside the corridor
    assert g.free_distance(post) < 0.3
    theta = g.way_out(post, prefer=-1.0)
    assert theta is not None and theta > 0.0  # to the left, away from it, whatever the policy prefers
    turned = post_scan(0.0, 0.0, theta, 0.45, -0.75, 0.2)
    assert g.free_distance(turned) >= 0.3  # free as asked
    less = post_scan(0.0, 0.0, theta - math.radians(5), 0.45, -0.75, 0.2)
    assert g.free_distance(less) < 0.3  # and the nearest such heading (in 5 degree steps)
    assert g.way_out(np.full(BEAMS, 0.7)) is None  # walled in: none
    assert g.way_out(np.full(BEAMS, RANGE)) == 0.0  # straight ahead is free: exactly 0 (the step then drives on)


def _slide(cfg: GuardConfig, steps: int = 80) -> tuple[float, float, float, int]:
    """A pid leader whose goal lies straight ahead, past a post whose edge reaches 0.05 m into the grown corridor:
    how far it gets, its closest gap to the post, and the guard's slides."""
    d = scenario_dict(duration=20.0)
    d["robots"] = [{"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0]}]
    d["formation"] = {"leader": 0, "goal": [8.0, 0.0], "slots": {}}
    d["robot"]["lidar"] = {"beams": BEAMS, "fov_deg": 180, "range": RANGE, "noise_std": 0.0}
    d["robot"]["stuck"] = {"enabled": False}  # the guard alone
    sc = parse_scenario(d)
    pl = StepPipeline(sc, 0, policy="pid", config=StepConfig(guard=cfg))
    x = y = yaw = v = w = 0.0
    gap = math.inf
    cx, cy, rad = 0.6, -0.75, 0.2
    for k in range(steps):
        t = k * sc.dt
        scan = Scan(id=0, stamp=t, step=k, angle_min=-FOV / 2, angle_increment=FOV / (BEAMS - 1), range_max=RANGE,
                    ranges=post_scan(x, y, yaw, cx, cy, rad).tolist())
        odo = OdomSample(t=t, v=v, w=w, pose=(x, y, yaw))
        out = pl.step(StepInputs(step=k, t=t, t_run=t, now=t, odometry=(odo,), scan=scan, scan_t=t))
        v, w = out.v, out.w
        x, y, yaw = arc_step(x, y, yaw, v, w, sc.dt)
        gap = min(gap, math.hypot(x - cx, y - cy) - rad - 0.5)
    return x, y, gap, pl.guard.slides


def test_a_robot_the_guard_holds_takes_the_way_out_and_goes_on():
    """The pid aims straight at its goal, past a post whose edge is inside the grown corridor: the guard holds it (no
    turn comes from the pid, its goal is dead ahead). Held 1 s, it turns to the nearest free heading and drives on."""
    x, _, gap, slides = _slide(GuardConfig(margin=0.1, slide_after_s=1.0))
    assert slides > 0 and x > 1.5 and gap > 0.0  # past the post, never touching it
    x_held, _, _, none = _slide(GuardConfig(margin=0.1, slide_after_s=0.0))
    assert none == 0 and x_held < 0.5  # without the way out it stands where the guard first held it


# --- the stop deadline (stack/agents/cli.py): a control step that outlasts the stop signal ---------------
class _Driver:
    def __init__(self):
        self.stops = 0

    def stop(self):
        self.stops += 1


class _Busy:
    """An agent still inside its control step."""

    def __init__(self, rid: int):
        self.id, self.driver = rid, _Driver()


def test_a_step_still_busy_after_the_stop_signal_gets_zero_from_beside_it_then_the_process_ends():
    import threading

    from stack.agents.cli import stop_deadline

    busy = _Busy(7)
    exits: list[int] = []
    done = threading.Event()
    stop_deadline(lambda: busy, done, grace=0.05, exit_=exits.append)
    assert busy.driver.stops == 1 and exits == [0]  # zero velocity first, then the exit
    done.set()
    stop_deadline(lambda: busy, done, grace=0.05, exit_=exits.append)
    assert busy.driver.stops == 1 and exits == [0]  # the agent had returned: nothing to do


def test_the_stop_deadline_is_armed_once_by_the_first_signal_even_after_the_world_said_done():
    """The world's "done" stops an agent (its stop event set) before the fleet's SIGTERM comes; a Q-learning leader
    then still mid-plan was SIGKILLed 10 s later on held-out courses: the deadline must run from that signal."""
    import threading

    from stack.agents.cli import StopDeadline

    busy = _Busy(3)
    exits: list[int] = []
    dl = StopDeadline(lambda: busy, threading.Event(), grace=0.05, exit_=exits.append)
    dl.arm()
    first = dl.thread
    dl.arm()  # a second signal: the same deadline
    assert dl.thread is first
    first.join(5)
    assert busy.driver.stops == 1 and exits == [0]
