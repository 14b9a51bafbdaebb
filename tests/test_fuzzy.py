"""Chang 2020 (stack.policies.fuzzy, stack.train.fuzzy/fuzzyworld): TSK, BF mirror, supervisor, PSO, MRC."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from stack.policies.base import Observation
from stack.policies.fuzzy import FuzzyConfig, FuzzyPolicy, hand_set_params, load_params, make_fuzzy, make_fuzzy_lstm
from stack.policies.fuzzy.mrc import (Coordinator, FlcSr, LstmMrc, LstmWeights, MrcConfig, PeerEstimate, beta,
                                      interpolate_alphas)
from stack.policies.fuzzy.pso import PsoConfig, pso
from stack.policies.fuzzy.rbc import (BF_LEFT, BF_RIGHT, TS, BehaviourSupervisor, BoundaryFollower, SupervisorConfig,
                                      sectors)
from stack.policies.fuzzy.tsk import TSK


# -- TSK (eq. 3-6) ------------------------------------------------------------------------------
def test_tsk_one_input_hand_computed():
    t = TSK(m=[[0.0], [1.0]], sigma=[[1.0], [1.0]], a=[[0.0], [1.0]])
    assert t([0.5])[0] == pytest.approx(0.5)
    e = math.exp(-1.0)  # x = 0: mu_1 = 1, mu_2 = exp(-1)
    assert t([0.0])[0] == pytest.approx(e / (1 + e))


def test_tsk_product_and_vector_consequent_hand_computed():
    t = TSK(m=[[0.0, 0.0], [1.0, 1.0]], sigma=[[1.0, 2.0], [1.0, 1.0]], a=[[2.0, 1.0], [-1.0, 3.0]])
    phi1 = math.exp(-0.25) * math.exp(-0.25)  # x = (0.5, 1): ((0.5 - 0) / 1)^2, ((1 - 0) / 2)^2
    phi2 = math.exp(-0.25) * 1.0
    y = t([0.5, 1.0])
    assert y[0] == pytest.approx((2 * phi1 - phi2) / (phi1 + phi2))
    assert y[1] == pytest.approx((1 * phi1 + 3 * phi2) / (phi1 + phi2))


def test_tsk_far_from_every_centre_is_defined():
    t = TSK(m=[[0.0], [1.0]], sigma=[[0.01], [0.01]], a=[[-1.0], [1.0]])
    assert t([100.0])[0] == pytest.approx(1.0)  # eq. (6) is 0/0 in floats; the nearer rule wins


def test_tsk_vector_round_trip():
    t = TSK.from_dict(hand_set_params()["bf_left"])
    u = TSK.from_vector(t.to_vector(), 10, 4, 1)
    assert np.allclose(u.m, t.m) and np.allclose(u.sigma, t.sigma) and np.allclose(u.a, t.a)


# -- sectors, BF mirror (eq. 15-16) --------------------------------------------------------------
def test_sectors_right_to_left():
    scan = np.full(160, 5.0)
    scan[0] = 1.0  # rightmost beam -> L1
    scan[-1] = 2.0  # leftmost -> L8
    scan[80] = 3.0  # just left of the heading -> L5
    L = sectors(scan, math.pi, 5.0)
    assert L[0] == 1.0 and L[7] == 2.0 and L[4] == 3.0 and (L[[1, 2, 3, 5, 6]] == 5.0).all()
    assert np.allclose(sectors(scan[::-1], math.pi, 5.0), L[::-1])


@pytest.mark.parametrize("params", ["hand", "shipped"])
def test_right_bf_on_mirrored_scan_gives_negated_angle(params):
    p = hand_set_params() if params == "hand" else load_params()
    bf = BoundaryFollower(TSK.from_dict(p["bf_left"]))
    rng = np.random.default_rng(0)
    for _ in range(50):
        L = rng.uniform(0.3, 5.0, 8)
        assert bf.right(L[::-1]) == pytest.approx(-bf.left(L), abs=1e-12)


def test_left_bf_turns_away_from_a_near_wall_and_toward_a_far_one():
    bf = BoundaryFollower(TSK.from_dict(load_params()["bf_left"]))
    wall = lambda d: np.array([5, 5, 5, 5, min(5, 2.61 * d), 1.41 * d, 1.08 * d, d])  # straight wall at d on the left
    assert bf.left(wall(0.55)) < 0 < bf.left(wall(1.45))


# -- supervisor (Fig. 5) -------------------------------------------------------------------------
def _L(front=5.0, left=5.0, right=5.0):
    L = np.full(8, 5.0)
    L[3] = L[4] = front
    L[6:] = np.minimum(L[6:], left)  # L7, L8
    L[:2] = np.minimum(L[:2], right)  # L1, L2
    return L


def test_supervisor_switching_rule():
    s = BehaviourSupervisor(SupervisorConfig(d_detect=1.2, c_min=100, d_release=3.0))
    assert s.step(_L(), 20.0, 0.0) == TS  # nothing in range
    assert s.step(_L(front=4.0), 20.0, 0.0) == TS  # far obstacle
    assert s.step(_L(front=1.0, left=0.9), 20.0, 0.0) == BF_LEFT  # obstacle ahead, nearer on the left
    assert s.d1 == 20.0 and s.c_step == 0
    # the target direction is free again, but no progress (d2 >= d1): BF is kept up to c_min steps
    for _ in range(100):
        assert s.step(_L(front=5.0, left=0.8), 20.5, 0.0) == BF_LEFT
    assert s.step(_L(front=5.0, left=0.8), 20.5, 0.0) == TS  # c_step > 100: leaves BF
    # again, nearer on the right; progress (d2 < d1) with a free target direction ends BF at once
    assert s.step(_L(front=1.0, right=0.9), 19.0, 0.0) == BF_RIGHT
    assert s.step(_L(front=1.0, right=0.9), 18.8, 0.0) == BF_RIGHT  # target direction blocked
    assert s.step(_L(front=5.0, right=0.9), 18.5, 0.0) == TS
    # a target behind the robot is never "free": BF goes on
    s.step(_L(front=1.0, left=0.9), 10.0, 0.0)
    assert s.step(_L(front=5.0, left=0.9), 9.0, math.radians(150)) == BF_LEFT


# -- PSO (eq. 17-18) -----------------------------------------------------------------------------
def test_pso_finds_the_minimum_of_a_known_function():
    c = np.array([1.5, -2.0, 0.5])
    f = lambda x: float(np.sum((x - c) ** 2) + 0.5 * np.sin(3 * (x - c)).dot(np.sin(3 * (x - c))))
    res = pso(f, [-5] * 3, [5] * 3, PsoConfig(particles=20, iterations=120), seed=1)
    assert np.allclose(res.best, c, atol=1e-2) and res.best_f < 1e-3
    assert all(a >= b for a, b in zip(res.curve, res.curve[1:]))  # best-so-far is monotone


def test_pso_rosenbrock():
    f = lambda x: float((1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2)
    res = pso(f, [-2, -2], [2, 2], PsoConfig(particles=30, iterations=300), seed=0)
    assert np.allclose(res.best, [1, 1], atol=0.05)


# -- MRC (eq. 1-2, 7-14), decentralised ----------------------------------------------------------
def test_interpolation_eq1_and_beta_eq8():
    a = interpolate_alphas(0.8, 1.2, 5)
    assert np.allclose(a, [0.8, 0.9, 1.0, 1.1, 1.2])
    assert beta(1.0, 10.0, 10.0) == 0.0  # the farthest robot is not turned
    assert beta(0.5, 5.0, 10.0) == pytest.approx(1.0)  # sqrt((1 / 0.5) (1 - 0.5))


@pytest.mark.parametrize("kind", ["flc", "lstm"])
def test_farthest_robot_gets_alpha_at_least_the_nearest(kind):
    p = load_params()
    rng = np.random.default_rng(3)
    for _ in range(60):
        n = int(rng.integers(2, 7))
        d = rng.uniform(1, 50, n)
        v = rng.uniform(0.2, 0.8, n)
        coords = []
        for i in range(n):  # every robot computes its own alpha from the others' states
            core = FlcSr(TSK.from_dict(p["flc_sr"])) if kind == "flc" else LstmMrc(LstmWeights.from_dict(p["lstm"]))
            c = Coordinator(core, MrcConfig())
            c.v = v[i]
            co = c.step(d[i], [PeerEstimate(d[j], v[j]) for j in range(n) if j != i])
            coords.append(co)
        near, far = int(np.argmin(d)), int(np.argmax(d))
        assert coords[near].rank == 1 and coords[far].rank == n
        assert coords[far].alpha >= coords[near].alpha
        assert coords[far].beta == 0.0 and not coords[far].adjust
        assert all(0.2 - 1e-9 <= co.v <= 0.8 + 1e-9 for co in coords)  # eq. (2) bounded: nobody stops


def test_decentralised_agents_agree_and_stale_peers_drop_out():
    p = load_params()
    d, v = [10.0, 25.0, 40.0], [0.5, 0.5, 0.5]
    outs = []
    for i in range(3):
        c = Coordinator(FlcSr(TSK.from_dict(p["flc_sr"])))
        co = c.step(d[i], [PeerEstimate(d[j], v[j]) for j in range(3) if j != i])
        outs.append(co.inputs)
    assert np.allclose(outs[0], outs[1]) and np.allclose(outs[1], outs[2])  # same inputs -> same alpha_1, alpha_n
    c = Coordinator(FlcSr(TSK.from_dict(p["flc_sr"])), MrcConfig(max_age=3.0))
    co = c.step(10.0, [PeerEstimate(40.0, 0.5, age=5.0)])
    assert co.n == 1 and co.alpha == 1.0  # alone: nothing to coordinate


@pytest.mark.parametrize("kind", ["flc", "lstm"])
def test_terminal_matching_inside_d_near_all_gives_every_robot_the_farthests_time_to_go(kind):
    """Within d_near_all a nearer robot drives at most v_n d_i / d_n (so it arrives with the farthest);
    outside it, or with terminal_match off, eq. (2) alone."""
    p = load_params()

    def core():
        return FlcSr(TSK.from_dict(p["flc_sr"])) if kind == "flc" else LstmMrc(LstmWeights.from_dict(p["lstm"]))

    c = Coordinator(core(), MrcConfig())
    c.v = 0.8
    co = c.step(6.0, [PeerEstimate(8.0, 0.8)])
    assert co.rank == 1 and co.v == pytest.approx(max(0.2, min(c.v, 0.8 * 6.0 / 8.0)))
    assert co.v <= 0.6 + 1e-9  # time to go 6 / v >= 8 / 0.8
    off = Coordinator(core(), MrcConfig(terminal_match=False))
    off.v = 0.8
    assert off.step(6.0, [PeerEstimate(8.0, 0.8)]).v == pytest.approx(off.v)
    far = Coordinator(core(), MrcConfig())
    far.v = 0.8
    assert far.step(16.0, [PeerEstimate(18.0, 0.8)]).v == pytest.approx(far.v)  # not every robot within 10 m
    last = Coordinator(core(), MrcConfig())
    last.v = 0.8
    assert last.step(8.0, [PeerEstimate(6.0, 0.8)]).v == pytest.approx(last.v)  # the farthest is not capped


def test_no_mrc_keeps_constant_speed():
    c = Coordinator(None, MrcConfig(v0=0.5))
    for _ in range(5):
        co = c.step(10.0, [PeerEstimate(40.0, 0.5)])
    assert co.v == 0.5 and not co.adjust


def test_lstm_forward_matches_equations():
    rng = np.random.default_rng(0)
    w = LstmWeights.from_vector(rng.normal(0, 1, LstmWeights.N_PARAMS))
    m = LstmMrc(w)
    x = rng.normal(0, 1, 5)
    a1, an = m(x)
    sig = lambda z: 1 / (1 + np.exp(-z))
    z = np.tanh(w.W[0] @ x + 0.5)
    i = sig(w.W[1] @ x + 0.5)
    c = z * i  # c^{k-1} = 0: the forget gate and peepholes on c^{k-1} drop out
    o = sig(w.W[3] @ x + w.p[2] * c + 0.5)
    y = np.tanh(c) * o
    assert (a1, an) == pytest.approx(tuple(1 + 0.5 * y))
    m.reset()
    assert m(x) == pytest.approx((a1, an))


# -- the policy --------------------------------------------------------------------------------
def test_policy_drives_to_the_goal_and_stops():
    pol = make_fuzzy()
    assert pol.hybrid is False and pol.name == "fuzzy" and make_fuzzy_lstm().name == "fuzzy-lstm"
    clear = np.full((1, 180), 5.0)
    v, w = pol.act(Observation(d_g=10.0, alpha_g=0.5, v=0, w=0, scans=clear, x=0, y=0, target=(10, 0)))
    assert v > 0 and w > 0  # target to the left: turn left
    assert pol.act(Observation(d_g=0.2, alpha_g=0.0, v=0, w=0, scans=clear, x=9.8, y=0, target=(10, 0))) == (0.0, 0.0)


def test_factory_reads_robot_config_and_coordinator():
    from stack.scenario import load_scenario

    sc = load_scenario("scenarios/chang-three.yaml")
    assert sc.coordination == "arrival_time" and len(sc.robots) == 3
    for coord, name in (("flc", "fuzzy"), ("lstm", "fuzzy-lstm"), ("none", "fuzzy-nomrc")):
        pol = make_fuzzy(sc.robots[0], coordinator=coord)
        assert pol.name == name and pol.fov == pytest.approx(math.pi) and pol.v_max == 1.0
    with pytest.raises(ValueError):
        FuzzyPolicy(FuzzyConfig(coordinator="central"))


def test_shipped_params_load_with_the_right_shapes():
    from stack.policies.fuzzy.policy import PARAMS_FILE

    d = json.loads(PARAMS_FILE.read_text())
    assert np.array(d["bf_left"]["m"]).shape == (10, 4)
    assert np.array(d["flc_sr"]["a"]).shape == (5, 2)
    assert LstmWeights.from_dict(d["lstm"]).to_vector().size == LstmWeights.N_PARAMS


# -- the numpy world -----------------------------------------------------------------------------
def test_ray_cast_analytic():
    from stack.train.fuzzyworld import World, ray_cast

    w = World(boxes=[(5.0, 0.0, 1.0, 1.0, 0.0)], circles=[(0.0, 3.0, 0.5)])
    r = ray_cast(0.0, 0.0, np.array([0.0, math.pi / 2, math.pi]), w.segs, w.circ, 10.0)
    assert r == pytest.approx([4.0, 2.5, 10.0])
    assert w.surface_distance(2.0, 0.0) == pytest.approx(2.0)


def test_three_robots_arrive_together_in_the_numpy_world():
    from stack.train.fuzzyworld import RobotSpec, SimConfig, World, arrival_goals, run

    goals = arrival_goals((0.0, 0.0), 3)
    starts = [(12.0, 1.0), (-6.0, 18.0), (-15.0, -22.0)]
    robots = [RobotSpec((sx, sy, math.atan2(-sy, -sx)), g) for (sx, sy), g in zip(starts, goals)]
    world = World(boxes=[(6.0, 0.5, 1.0, 1.0, 0.0)])
    res = {}
    for coord in ("none", "flc"):
        pols = [make_fuzzy(None, coordinator=coord) for _ in robots]
        res[coord] = run(world, robots, pols, SimConfig(max_steps=1500, beams=40))
        assert res[coord].collisions_robot == 0 and res[coord].collisions_obstacle == 0
    assert res["none"].spread is not None and res["flc"].spread is not None
    assert res["flc"].spread < res["none"].spread / 3


def test_policy_uses_neighbour_states_when_the_observation_has_them():
    pol = make_fuzzy()
    obs = Observation(d_g=10.0, alpha_g=0.0, v=0, w=0, scans=np.full((1, 180), 5.0), x=0, y=0, target=(10, 0))
    obs.neighbour_states = np.array([[40.0, 0.0, 0.0, 0.7, 0.0, 0.5]])  # x, y, yaw, v, w, age
    pol.act(obs)
    assert pol.last.n == 2 and pol.last.rank == 1 and pol.last.inputs[3] == pytest.approx(0.7)


def test_policy_ranks_by_the_distances_peers_report_to_their_own_goals():
    """A peer 30 m from this robot's goal but 5 m from its own (reported, State.d_goal) is the nearest robot;
    with ``peer_goals=False`` the same peer is ranked by its distance to this robot's goal (the farthest)."""
    obs = Observation(d_g=10.0, alpha_g=0.0, v=0, w=0, scans=np.full((1, 180), 5.0), x=0, y=0, target=(10, 0),
                      neighbour_states=np.array([[40.0, 0.0, 0.0, 0.5, 0.0, 0.0]]), neighbour_d_goal=np.array([5.0]))
    pol = make_fuzzy()
    pol.act(obs)
    assert pol.last.n == 2 and pol.last.rank == 2  # this robot (10 m) is the farthest
    assert pol.last.inputs[0] * pol.mrc.cfg.d_scale == pytest.approx(5.0)
    old = FuzzyPolicy(FuzzyConfig(peer_goals=False))
    old.act(obs)
    assert old.last.rank == 1 and old.last.inputs[1] * old.mrc.cfg.d_scale == pytest.approx(30.0)
    obs.neighbour_d_goal = np.array([math.nan])  # the peer did not say: its distance to this robot's goal
    pol.act(obs)
    assert pol.last.rank == 1


def test_arrival_detour_passes_a_standing_robot_on_the_goals_side():
    """Within detour_radius of its goal, a robot whose way is blocked by a standing (or creeping) neighbour
    steers along the tangent past it on the goal's side, 2 radius + detour_margin off its centre."""
    def obs(*states):
        return Observation(d_g=2.5, alpha_g=0.0, v=0, w=0, scans=np.full((1, 180), 5.0), x=0, y=0, yaw=0.0,
                           target=(2.5, 0), neighbour_states=np.array(states, float).reshape(-1, 6))

    pol = make_fuzzy()
    clear = 2 * pol.radius + pol.cfg.detour_margin
    b = math.atan2(0.1, 1.2)  # a robot standing just left of the line to the goal: pass it on the right
    heading = pol._detour(obs([1.2, 0.1, 0.0, 0.0, 0.0, 0.0]), 2.5, 0.0)
    assert heading == pytest.approx(b - math.asin(clear / math.hypot(1.2, 0.1)))
    assert pol._detour(obs([1.2, -0.1, 0.0, 0.1, 0.0, 0.0]), 2.5, 0.0) > 0  # just right of it, creeping: the left
    assert pol._detour(obs([1.2, 0.1, 0.0, 0.8, 0.0, 0.0]), 2.5, 0.0) is None  # driving: not a standing obstacle
    assert pol._detour(obs([1.2, 1.5, 0.0, 0.0, 0.0, 0.0]), 2.5, 0.0) is None  # beside the way, not in it
    assert pol._detour(obs([4.0, 0.0, 0.0, 0.0, 0.0, 0.0]), 2.5, 0.0) is None  # beyond the goal
    assert pol._detour(obs([1.2, 0.1, 0.0, 0.0, 0.0, 0.0], [1.0, -1.0, 0, 0, 0, 0]), 2.5, 0.0) is None  # both sides shut
    walled = obs([1.2, 0.1, 0.0, 0.0, 0.0, 0.0])
    walled.scans = np.full((1, 180), 5.0)
    walled.scans[0, 30:60] = 0.8  # a wall 0.8 m away along the tangent (-56 deg): no detour into it
    assert pol._detour(walled, 2.5, 0.0) is None
    near = pol._detour(obs([0.7, 0.0, 0.0, 0.0, 0.0, 0.0]), 2.5, 0.0)
    assert math.pi / 2 < abs(near) <= 3 * math.pi / 4  # nearer than the clearance: away from it first
    v, w = make_fuzzy().act(obs([1.2, 0.1, 0.0, 0.0, 0.0, 0.0]))
    assert w < -0.5  # the policy takes the detour: a right turn toward the tangent
    v, w = FuzzyPolicy(FuzzyConfig(detour_radius=0.0)).act(obs([1.2, 0.1, 0.0, 0.0, 0.0, 0.0]))
    assert abs(w) < 1e-9  # off: straight at the goal (the scan shows nothing; the paper's TS)


def test_phase1_fitness_of_the_shipped_bf_controller_is_a_success():
    from stack.train.fuzzy import T_SUC, phase1_fitness

    assert phase1_fitness(TSK.from_dict(load_params()["bf_left"]).to_vector()) == pytest.approx(1.0 / T_SUC)
    assert phase1_fitness(np.zeros(90)) > 1.0 / T_SUC  # a controller that never turns fails early


def test_phase2_fitness_eq21_as_read_and_nobody_arriving_is_the_worst(monkeypatch):
    import stack.train.fuzzyworld as fw
    from stack.train.fuzzy import phase2_score

    def fake(arrivals):
        return lambda *a, **k: fw.RunResult(list(arrivals), 0, 0, 1.0, 1.0, 100)

    vec = TSK.from_dict(hand_set_params()["flc_sr"]).to_vector()
    bf = load_params()["bf_left"]
    monkeypatch.setattr(fw, "run", fake([500, 520, 510]))
    f, spreads, completes, cols = phase2_score(vec, "flc", bf, 1000)
    assert f == pytest.approx(10 * 20 + 0.1 * 520) and spreads == [20, 20] and completes == [520, 520]  # Table 1's reading
    monkeypatch.setattr(fw, "run", fake([None, None, None]))
    assert phase2_score(vec, "flc", bf, 1000)[0] == pytest.approx(10 * 1000 + 0.1 * 1000)


def test_factory_robot_fuzzy_settings():
    from conftest import scenario_dict
    from stack.scenario import ScenarioError, parse_scenario

    d = scenario_dict()
    d["robot"]["fuzzy"] = {"coordinator": "none", "target": [1, 2], "v_min": 0.3, "c_min": 50}
    pol = make_fuzzy(parse_scenario(d).robots[0])
    assert pol.name == "fuzzy-nomrc" and pol.cfg.target == (1, 2) and pol.mrc.cfg.v_min == 0.3
    assert pol.rbc.supervisor.cfg.c_min == 50
    d["robot"]["fuzzy"] = {"nonsense": 1}
    with pytest.raises(ScenarioError, match="robot.fuzzy.nonsense: unknown field"):
        parse_scenario(d)


@pytest.mark.parametrize("key, value, words", [
    ("detour_radius", -1, "detour_radius: must be >= 0, got -1"),
    ("guard", "x", "guard: expected a number, got text ('x')"),
    ("t_brake", 0, "t_brake: must be > 0, got 0"),
    ("c_min", 1.5, "c_min: expected an integer, got a number (1.5)"),
    ("v_min", float("nan"), "v_min: expected a finite number, got nan"),
    ("v_min", -0.1, "v_min: must be >= 0, got -0.1"),
    ("terminal_match", 1, "terminal_match: expected true or false, got a number (1)"),
])
def test_robot_fuzzy_values_are_checked_where_the_scenario_is_read(key, value, words):
    """A bad value in robot.fuzzy (FuzzyConfig, MrcConfig or SupervisorConfig) is one line naming it,
    when the scenario is read, not a traceback in an agent at its first step."""
    from conftest import scenario_dict
    from stack.scenario import ScenarioError, parse_scenario

    d = scenario_dict()
    d["robot"]["fuzzy"] = {key: value}
    with pytest.raises(ScenarioError) as e:
        parse_scenario(d, "s.yaml")
    assert str(e.value) == f"s.yaml: robot.fuzzy.{words}"

