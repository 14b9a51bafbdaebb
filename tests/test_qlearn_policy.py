"""``--policy qlearn`` online (Fan 2021, issue 8): the leader's lidar grid and Q-L5 replanning, the
follower's eq. (12)-(13) tracking, and closed loops in a tiny numpy world (unicycles, a 2-D lidar
ray-cast against circles; no pybullet)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from stack.planning.tracking import tracking_cost
from stack.policies.base import Observation
from stack.policies.qlearn import (QlearnPolicy, QlearnPolicyConfig, Polyline, dilate, gpf_choice, make_qlearn,
                                   reachable, string_pull)
from stack.train.drlworld import ray_cast
from stack.scenario import ScenarioError, load_scenario, parse_scenario

ROOT = Path(__file__).resolve().parents[1]
BEAMS, FOV, RANGE = 180, math.pi, 5.0
REL = np.linspace(-FOV / 2, FOV / 2, BEAMS)


# --- a tiny world ---------------------------------------------------------------------------

def raycast(x: float, y: float, yaw: float, circles) -> np.ndarray:
    """Ranges of a 180-beam, 180-degree, 5 m lidar at (x, y, yaw) against circles (cx, cy, R)."""
    c = np.asarray(circles, float).reshape(-1, 3)
    return ray_cast(np.float64(x), np.float64(y), np.float64(yaw), c, np.zeros((0, 5)), REL, 0.0, RANGE)


def observe(x, y, yaw, target, scan, neighbours=(), goal_velocity=(0.0, 0.0), dt=0.1) -> Observation:
    """An observation as the decision layer builds it; ``neighbours``: world positions of other robots."""
    nb = [(math.hypot(nx - x, ny - y), math.atan2(ny - y, nx - x) - yaw) for nx, ny in neighbours]
    nb = np.array(sorted(nb, reverse=True), float).reshape(-1, 2)
    return Observation(d_g=math.hypot(target[0] - x, target[1] - y),
                       alpha_g=math.atan2(target[1] - y, target[0] - x) - yaw, v=0.0, w=0.0, neighbours=nb,
                       scans=np.asarray(scan, float)[None, :], goal_velocity=goal_velocity, yaw=yaw, scan_range=RANGE,
                       dt=dt, x=x, y=y, target=(float(target[0]), float(target[1])))


def leader(**cfg) -> QlearnPolicy:
    return QlearnPolicy(QlearnPolicyConfig(**cfg), role="leader", radius=0.5, v_max=1.0, w_max=1.0,
                        lidar_fov=FOV, lidar_range=RANGE, seed=0)


def follower(**cfg) -> QlearnPolicy:
    return QlearnPolicy(QlearnPolicyConfig(**cfg), role="follower", radius=0.5, v_max=1.0, w_max=1.0,
                        lidar_fov=FOV, lidar_range=RANGE, seed=0)


# --- (a) the grid -----------------------------------------------------------------------------

def test_grid_marks_beam_endpoints_inflated_and_ignores_beams_on_neighbours():
    pol = leader()
    scan = np.full(BEAMS, RANGE)
    wall = np.abs(REL) < math.radians(3)  # a few beams straight ahead end at 2.1 m
    scan[wall] = 2.1
    nb = (3.0 * math.cos(1.0), 3.0 * math.sin(1.0))  # a robot at 3 m, bearing 1 rad: its front at 2.5 m
    on_nb = np.abs(REL - 1.0) < math.radians(8)
    scan[on_nb] = 2.5
    pol.act(observe(0.0, 0.0, 0.0, (20.0, 0.0), scan, neighbours=[nb]))
    g = pol.grid
    occ = g.occupied()
    hit_cell = g.cell_of(2.1, 0.0)
    assert occ[hit_cell]
    assert not occ[g.cell_of(2.5 * math.cos(1.0), 2.5 * math.sin(1.0))]  # the neighbour marks nothing
    assert not occ[g.cell_of(1.0, 0.0)] and not occ[g.cell_of(0.0, 0.0)]  # passed by beams: free
    assert occ.sum() == len({g.cell_of(2.1 * math.cos(a), 2.1 * math.sin(a)) for a in REL[wall]})
    # inflation: radius 0.5 + clearance 0.4 over 0.5 m cells, + half a cell = 2.3 cells centre to centre
    blocked = g.blocked(0.5)
    i, j = hit_cell
    assert blocked[i - 2, j] and blocked[i - 2, j + 1] and blocked[i, j + 2]  # 2 and sqrt(5) = 2.24 cells away
    assert not blocked[i - 3, j] and not blocked[i - 2, j + 2]  # 3 and 2.83 cells away
    # noisy max-range beams (4.99 m) are not hits
    pol2 = leader()
    pol2.act(observe(0.0, 0.0, 0.0, (20.0, 0.0), np.full(BEAMS, RANGE - 0.01)))
    assert not pol2.grid.occupied().any()


def test_dilate_reachable_and_string_pull_on_hand_cases():
    m = np.zeros((7, 7), bool)
    m[3, 3] = True
    assert dilate(m, 1.0).sum() == 5 and dilate(m, 1.5).sum() == 9
    b = np.zeros((6, 6), bool)
    b[2, :] = True
    assert not reachable(b, (0, 0), (5, 5))
    b[2, 5] = False
    assert reachable(b, (0, 0), (5, 5))
    straight = [(x, 1) for x in range(6)]
    assert string_pull(straight, np.zeros((8, 4), bool)) == [(0, 1), (5, 1)]
    wall = np.zeros((8, 6), bool)
    wall[3, 0:3] = True  # the straight line from (1, 1) to (6, 1) is cut; the path over (3, 4) is not
    bent = [(1, 1), (2, 2), (2, 3), (3, 4), (4, 3), (5, 2), (6, 1)]
    pulled = string_pull(bent, wall)
    assert pulled[0] == (1, 1) and pulled[-1] == (6, 1) and 2 < len(pulled) < len(bent)
    line = Polyline([(0, 0), (2, 0), (2, 2)])
    assert line.length == pytest.approx(4.0)
    assert line.project(1.0, 0.3) == pytest.approx((1.0, 0.3))
    assert line.turn_within(0.5, 3.0) == pytest.approx(math.pi / 2)
    assert line.point_at(3.0) == pytest.approx([2.0, 1.0])


# --- (a) replanning -----------------------------------------------------------------------------

def test_replans_when_an_obstacle_appears_on_the_path_and_not_when_nothing_changes():
    pol = leader()
    free = np.full(BEAMS, RANGE)
    for _ in range(30):  # standing still, nothing new: one plan only
        pol.act(observe(0.0, 0.0, 0.0, (10.0, 0.0), free))
    assert pol.counters["plans"] == 1 and pol.counters["replan_initial"] == 1
    assert pol.path is not None and pol.path.p[-1] == pytest.approx([10.0, 0.0])
    side = raycast(0.0, 0.0, 0.0, [(0.5, 4.3, 0.3)])  # something far to the side of the path
    for _ in range(5):
        pol.act(observe(0.0, 0.0, 0.0, (10.0, 0.0), side))
    assert pol.counters["plans"] == 1
    circles = [(3.0, 0.0, 0.6)]  # a cylinder on the path
    for _ in range(5):
        pol.act(observe(0.0, 0.0, 0.0, (10.0, 0.0), raycast(0.0, 0.0, 0.0, circles)))
    assert pol.counters["replan_blocked"] >= 1 and pol.counters["warm_plans"] >= 1
    n = pol.counters["plans"]
    assert pol.result.converged
    samples = pol.path.samples(0.0, 0.05)
    assert np.hypot(samples[:, 0] - 3.0, samples[:, 1]).min() > 0.6 + 0.5  # the new path goes round it
    for _ in range(10):  # the same scan again: nothing new, no replan
        pol.act(observe(0.0, 0.0, 0.0, (10.0, 0.0), raycast(0.0, 0.0, 0.0, circles)))
    assert pol.counters["plans"] == n
    assert len(pol.plan_times) == n


def test_no_route_falls_back_to_driving_toward_the_goal_and_counts_it():
    pol = leader()
    free = np.full(BEAMS, RANGE)
    pol.act(observe(0.0, 0.0, 0.0, (10.0, 0.0), free))
    g = pol.grid
    i, _ = g.cell_of(4.0, 0.0)
    g.L[i, :] = 3.0  # a wall across the whole map (as if seen earlier)
    pol.act(observe(0.0, 0.0, 0.0, (10.0, 0.0), raycast(0.0, 0.0, 0.0, [(3.0, 0.0, 0.4)])))
    assert pol.counters["no_route"] == 1 and pol.path is None and pol.last["fallback"]
    v, w = pol.act(observe(0.0, 0.0, 0.0, (10.0, 0.0), free))
    assert v > 0  # drives toward the goal meanwhile


# --- (a) the follower's eq. (12)-(13) --------------------------------------------------------------

def test_follower_cost_is_eq_13_and_picks_the_free_direction_when_the_direct_one_is_blocked():
    cfg = QlearnPolicyConfig()
    p, aim = (0.0, 0.0), (3.0, 0.0)
    open_ = gpf_choice(p, aim, 0.0, np.zeros((0, 2)), np.zeros((0, 2)), cfg, 0.5)
    assert open_.theta == pytest.approx(0.0) and not open_.obstacle.any()
    # eq. (13) in cells: c * d_attr + R_static, with d_attr from the candidate one step (one cell) ahead
    for k in (0, 3, 8):
        end = (0.5 * math.cos(open_.thetas[k]) / 0.5, 0.5 * math.sin(open_.thetas[k]) / 0.5)
        assert open_.cost[k] == pytest.approx(tracking_cost(end, (6.0, 0.0), False, 0.09, 1.0))
    ang = np.linspace(-0.4, 0.4, 9)
    pts = np.column_stack([1.0 * np.cos(ang), 1.0 * np.sin(ang)])  # an obstacle 1 m straight ahead
    ch = gpf_choice(p, aim, 0.0, pts, np.zeros((0, 2)), cfg, 0.5)
    assert ch.obstacle[-1] and ch.obstacle[0]  # the direct candidate is an obstacle
    assert ch.cost[-1] == pytest.approx(0.09 * 5.0 + 1.0)
    assert not ch.blocked and abs(ch.theta) > math.radians(30) and abs(ch.theta) < math.radians(100)
    # a neighbour on the way counts too
    rob = gpf_choice(p, aim, 0.0, np.zeros((0, 2)), np.array([[1.2, 0.0]]), cfg, 0.5)
    assert rob.obstacle[-1] and not rob.blocked and abs(rob.theta) > math.radians(30)
    # through the policy: a follower whose slot lies behind a cylinder turns off and keeps moving
    pol = follower()
    circles = [(1.4, 0.0, 0.5)]
    v, w = pol.act(observe(0.0, 0.0, 0.0, (4.0, 0.0), raycast(0.0, 0.0, 0.0, circles)))
    assert abs(pol.last["theta"]) > math.radians(30) and not pol.last["blocked"] and abs(w) > 0.5
    # a follower at a resting slot stands still
    assert pol.act(observe(4.0, 0.0, 0.0, (4.02, 0.0), np.full(BEAMS, RANGE))) == (0.0, 0.0)


def test_make_qlearn_from_the_scenario():
    sc = load_scenario(ROOT / "scenarios" / "four-robot-obstacles.yaml")
    lead, fol = make_qlearn(sc.robot(0), seed=3), make_qlearn(sc.robot(1))
    assert lead.name == fol.name == "qlearn" and lead.hybrid is False and fol.hybrid is False
    assert lead.plans and not fol.plans and lead.seed == 3
    assert lead.hit_margin == pytest.approx(0.1)  # 4 x the 0.01 m lidar noise is less than the default
    with pytest.raises(ValueError, match="unknown qlearn keys"):
        QlearnPolicyConfig.from_dict({"cel": 0.5})
    assert QlearnPolicyConfig.from_dict({"cell": 0.25}).cell == 0.25


def test_scenario_qlearn_block_sets_the_grid_and_rejects_bad_fields():
    raw = load_scenario(ROOT / "scenarios" / "four-robot-obstacles.yaml").raw
    sc = parse_scenario(raw | {"robot": dict(raw["robot"]) | {"qlearn": {"cell": 0.25, "n_headings": 8}}})
    pol = make_qlearn(sc.robot(0))
    assert pol.cfg.cell == 0.25 and pol.cfg.n_headings == 8
    for bad, words in (({"cell": -0.5}, "robot.qlearn.cell: must be > 0"), ({"cel": 0.5}, "robot.qlearn.cel: unknown field"),
                       ({"max_rounds": 2.5}, "robot.qlearn.max_rounds: expected an integer"),
                       ({"evidence_min": 1.0}, "robot.qlearn.evidence_min: must be <= 0")):
        with pytest.raises(ScenarioError, match=words):
            parse_scenario(raw | {"robot": dict(raw["robot"]) | {"qlearn": bad}})


# --- (b) closed loops in the tiny world ------------------------------------------------------------

def _step(pose, v, w, dt=0.1):
    x, y, yaw = pose
    return x + v * math.cos(yaw) * dt, y + v * math.sin(yaw) * dt, yaw + w * dt


def test_leader_reaches_a_goal_20_m_away_past_two_cylinders_without_touching():
    circles = [(6.0, 0.2, 0.8), (13.0, -0.3, 0.8)]  # both across the straight line
    goal = (20.0, 0.0)
    pol = leader()
    pose = (0.0, 0.0, 0.0)
    clearance = math.inf
    for _ in range(800):
        v, w = pol.act(observe(*pose, goal, raycast(*pose, circles)))
        pose = _step(pose, v, w)
        clearance = min(clearance, min(math.hypot(pose[0] - cx, pose[1] - cy) - R for cx, cy, R in circles))
        if math.hypot(goal[0] - pose[0], goal[1] - pose[1]) < 0.15 and v == 0.0:
            break
    assert math.hypot(goal[0] - pose[0], goal[1] - pose[1]) < 0.5
    assert clearance > 0.5  # the body (radius 0.5) never touched a cylinder
    assert pol.counters["replan_blocked"] >= 1 and pol.counters["fallback"] == 0
    assert pol.counters["plans"] < 40  # replanning is rare, not every step


def test_follower_keeps_its_slot_behind_a_moving_leader_past_a_cylinder():
    circles = [(8.0, 2.5, 0.7)]  # on the follower's line, beside the leader's
    lead = (0.0, 0.0, 0.0)
    offset = (-2.1, 2.1)
    fpose = (-2.1, 2.1, 0.0)
    pol = follower()
    clearance, errs = math.inf, []
    for k in range(250):
        lv = 0.6 if lead[0] < 15.0 else 0.0
        slot = (lead[0] + offset[0], lead[1] + offset[1])
        scan = raycast(*fpose, circles + [(lead[0], lead[1], 0.5)])
        v, w = pol.act(observe(*fpose, slot, scan, neighbours=[lead[:2]], goal_velocity=(lv, 0.0)))
        fpose = _step(fpose, v, w)
        lead = _step(lead, lv, 0.0)
        clearance = min(clearance, math.hypot(fpose[0] - 8.0, fpose[1] - 2.5) - 0.7)
        assert math.hypot(fpose[0] - lead[0], fpose[1] - lead[1]) > 1.0  # never touches the leader
        errs.append(math.hypot(fpose[0] - slot[0], fpose[1] - slot[1]))
    assert clearance > 0.5
    assert max(errs[-20:]) < 0.3  # back on its slot once the leader has stopped
    assert max(errs) > 0.5  # it did have to leave the slot to pass the cylinder
