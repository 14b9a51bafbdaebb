"""One copy of each model (stack/models): the kinematics, the geometry and the observation builder,
and that the world, the EKF, the decision layer and the training worlds really use the same one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import scenario_dict
from stack.agents.decision import DecisionLayer, Neighbour
from stack.estimation.ekf import motion
from stack.estimation.pose import Pose
from stack.models.geometry import polar, polar_array, slot_offset, slot_position, wrap, wrap_array
from stack.models.kinematics import arc_step, arc_step_array, body_rates, wheel_speeds
from stack.models.observation import STALE_AFTER_S, neighbour_polar_array, neighbour_view
from stack.policies.drl.observation import D_COM, goal_features, neighbour_features
from stack.scenario import Slot, parse_scenario
from stack.train import fuzzyworld
from stack.train.drlworld import DrlWorld, WorldConfig

RNG = np.random.default_rng(7)
N = 2000
# poses and rates, with w exactly 0, inside the Taylor branch (|w dt / 2| < 1e-3), and large
X, Y, YAW = RNG.uniform(-50, 50, N), RNG.uniform(-50, 50, N), RNG.uniform(-math.pi, math.pi, N)
V = RNG.uniform(-1.5, 1.5, N)
W = np.concatenate([np.zeros(100), RNG.uniform(-0.02, 0.02, 400), RNG.uniform(-4, 4, N - 500)])


# --- kinematics -----------------------------------------------------------------------------------
@pytest.mark.parametrize("dt", [0.1, 0.05, 1.0])
def test_vectorised_and_scalar_arcs_agree(dt):
    """The heading bit for bit (the wrap uses exact operations only); x and y to an ulp, since numpy's SIMD
    sin/cos may round differently from the C library's (seen on one machine of this workplace, not another)."""
    xs, ys, yaws = arc_step_array(X, Y, YAW, V, W, dt)
    one = np.array([arc_step(*a, dt) for a in zip(X, Y, YAW, V, W)])
    np.testing.assert_array_equal(yaws, one[:, 2])
    np.testing.assert_array_max_ulp(xs, one[:, 0], maxulp=1)
    np.testing.assert_array_max_ulp(ys, one[:, 1], maxulp=1)


@pytest.mark.parametrize("w", [0.0, 1e-7, 0.3, -2.5])
def test_arc_step_is_the_exact_arc(w):
    """Against the closed-form circle (and a straight line at w = 0), over many steps."""
    x, y, yaw, v, dt = 1.0, -2.0, 0.4, 0.8, 0.1
    for _ in range(100):
        x, y, yaw = arc_step(x, y, yaw, v, w, dt)
    t = 100 * dt
    if w == 0.0:
        ex, ey = 1.0 + v * t * math.cos(0.4), -2.0 + v * t * math.sin(0.4)
    else:
        ex = 1.0 + v / w * (math.sin(0.4 + w * t) - math.sin(0.4))
        ey = -2.0 - v / w * (math.cos(0.4 + w * t) - math.cos(0.4))
    assert x == pytest.approx(ex, abs=1e-9) and y == pytest.approx(ey, abs=1e-9)
    assert yaw == pytest.approx(wrap(0.4 + w * t), abs=1e-12)


def test_wheel_speeds_and_body_rates_are_inverse():
    wl, wr = wheel_speeds(V, W, 0.5, 0.1)
    v, w = body_rates(wl, wr, 0.5, 0.1)
    np.testing.assert_allclose(v, V, atol=1e-12)
    np.testing.assert_allclose(w, W, atol=1e-12)
    assert wheel_speeds(1.0, 0.0, 0.5, 0.1) == (10.0, 10.0)
    assert wheel_speeds(0.0, 1.0, 0.5, 0.1) == (-2.5, 2.5)  # turning left: the right wheel forward


def test_world_ekf_and_training_worlds_move_alike():
    """The same (v, w) over the same period gives the same pose in the pybullet world, the EKF's motion
    model, the DRL training world and the fuzzy training world: the one exact arc."""
    from stack.sim_bridge.world import World

    v, w, dt = 0.7, 0.45, 0.1
    world = World(parse_scenario(scenario_dict(), "w.yaml"))
    try:
        x0, y0, yaw0 = float(world.x[0]), float(world.y[0]), float(world.yaw[0])
        world.step({0: (v, w)}, dt, exact={0})
        got_world = (float(world.x[0]), float(world.y[0]), float(world.yaw[0]))
    finally:
        world.close()
    expect = arc_step(x0, y0, yaw0, float(world.v[0]), float(world.w[0]), dt)
    assert got_world == expect
    got_ekf = tuple(motion(np.array([x0, y0, yaw0, world.v[0], world.w[0]]), dt)[:3, 0])
    assert got_ekf == expect

    dw = DrlWorld(1, 1, seed=0, cfg=WorldConfig(wheel_accel=1e9, noise_std=0.0, dt=dt))
    dw.x[:], dw.y[:], dw.yaw[:] = x0, y0, yaw0
    table = np.array([[v, w]])
    dw.step(np.zeros((1, 1), np.int64), table)
    assert (dw.x[0, 0], dw.y[0, 0], dw.yaw[0, 0]) == arc_step(x0, y0, yaw0, dw.v[0, 0], dw.w[0, 0], dt)
    assert dw.v[0, 0] == pytest.approx(v, abs=1e-12) and dw.w[0, 0] == pytest.approx(w, abs=1e-12)

    class Const:
        def reset(self):
            pass

        def act(self, obs):
            return v, w

    r = fuzzyworld.run(fuzzyworld.World(), [fuzzyworld.RobotSpec((x0, y0, yaw0), (1e3, 1e3))], [Const()],
                       fuzzyworld.SimConfig(dt=dt, max_steps=1), record=True)
    assert tuple(r.traj[0, 0]) == arc_step(x0, y0, yaw0, v, w, dt)


# --- geometry -------------------------------------------------------------------------------------
def test_wrap_scalar_and_array_agree_and_land_in_the_half_open_interval():
    a = np.concatenate([RNG.uniform(-40, 40, 1000), [math.pi, -math.pi, 0.0, 3 * math.pi, -3 * math.pi]])
    arr = wrap_array(a)
    np.testing.assert_array_equal(arr, [wrap(x) for x in a])
    assert (arr > -math.pi).all() and (arr <= math.pi).all()
    assert wrap(-math.pi) == math.pi and wrap(math.pi) == math.pi
    np.testing.assert_allclose(np.cos(arr), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(arr), np.sin(a), atol=1e-12)


def test_polar_scalar_and_array_agree():
    d, b = polar_array(X, Y, YAW, X[::-1], Y[::-1])
    one = np.array([polar((x, y), yaw, (tx, ty)) for x, y, yaw, tx, ty in zip(X, Y, YAW, X[::-1], Y[::-1])])
    np.testing.assert_array_equal(d, one[:, 0])
    # numpy's arctan2 against libm's: an ulp of the angle before the heading is taken off (1e-15 rad at most)
    np.testing.assert_allclose(b, one[:, 1], rtol=0, atol=1e-14)
    assert polar((1.0, 1.0), math.pi / 2, (1.0, 3.0)) == (2.0, 0.0)  # straight ahead
    assert polar((0.0, 0.0), 0.0, (0.0, -2.0)) == (2.0, -math.pi / 2)  # on the right


def test_slot_geometry_eq3():
    s = Slot(3.0, math.radians(150))
    assert slot_offset(s) == (3.0 * math.cos(s.psi), 3.0 * math.sin(s.psi))
    assert slot_position((2.0, -1.0), s) == pytest.approx((2.0 - 3.0 * math.sqrt(3) / 2, -1.0 + 1.5))


# --- observations ---------------------------------------------------------------------------------
def _scene(rng, n=4):
    """n robots: poses (n, 3), rates (n, 2), goals (n, 2)."""
    pose = np.column_stack([rng.uniform(-6, 6, n), rng.uniform(-6, 6, n), rng.uniform(-math.pi, math.pi, n)])
    return pose, rng.uniform(-1, 1, (n, 2)), rng.uniform(-10, 10, (n, 2))


def _agent_obs(i, pose, vw, goal, stamped, now, scans, comm_range, scan_range, dt):
    """Robot i's Observation through the agent's decision layer (an arrival-time peer: straight to its goal);
    ``stamped``: id -> (x, y, yaw, v, w, stamp, d_goal) as received."""
    layer = DecisionLayer(i, "peer", None, goal=tuple(goal), radius=0.3, comm_range=comm_range, scan_range=scan_range, dt=dt)
    nbs = {j: Neighbour(j, "peer", *r[:5], stamp=r[5], seq=1, d_goal=r[6]) for j, r in stamped.items()}
    p = Pose(float(pose[0]), float(pose[1]), float(pose[2]), float(vw[0]), float(vw[1]))
    return layer.decide(p, now, nbs, scans, math.inf).obs


def _assert_same(a, b):
    for k in vars(a):
        x, y = getattr(a, k), getattr(b, k)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=k)
        else:
            assert x == y, k


@pytest.mark.parametrize("seed", range(5))
def test_fuzzy_training_world_and_agent_build_the_same_observation(seed):
    """From one situation (poses, rates, what each robot last heard and when), the fuzzy training
    world and the agent's decision layer give identical Observations, field by field."""
    rng = np.random.default_rng(seed)
    pose, vw, goals = _scene(rng)
    cfg = fuzzyworld.SimConfig(comm_range=9.0, loss=1.0)  # nothing new arrives: the reports below stand
    radio = fuzzyworld._Radio(len(pose))
    k = 40
    for i in range(len(pose)):
        for j in range(len(pose)):
            if i != j:  # heard 0..3.5 s ago: some extrapolated, some capped at 1 s, some stale
                age_steps = int(rng.integers(0, 36))
                radio.last[i][j] = (*rng.uniform(-6, 6, 2), rng.uniform(-3, 3), *rng.uniform(-1, 1, 2),
                                    (k - age_steps) * cfg.dt, float(rng.uniform(0, 20)))
    scan = rng.uniform(0.2, 5.0, 40)
    seen = 0
    for i in range(len(pose)):
        reports = radio.reports(i, k, pose, vw, goals, cfg, rng)
        fw = fuzzyworld.observe(pose[i], vw[i], goals[i], reports, scan, cfg)
        now = k * cfg.dt
        heard = {j: h for j, h in enumerate(radio.last[i]) if h is not None and now - h[5] <= STALE_AFTER_S}
        ag = _agent_obs(i, pose[i], vw[i], goals[i], heard, now, scan[None, :], cfg.comm_range, cfg.range_max, cfg.dt)
        _assert_same(fw, ag)
        seen += len(fw.neighbours)
    assert seen > 0  # the comparison covered neighbours, not only empty arrays


@pytest.mark.parametrize("seed", range(5))
def test_drl_training_world_and_agent_build_the_same_network_inputs(seed):
    """The DRL training world's vectorised observation (goal and neighbour features, eq. 11-13)
    equals the agent's Observation normalised by the policy's own feature functions."""
    rng = np.random.default_rng(seed)
    w = DrlWorld(2, 2, seed=seed, cfg=WorldConfig(robots=5))
    w.x[:], w.y[:], w.yaw[:] = (rng.uniform(-8, 8, (2, 5)), rng.uniform(-8, 8, (2, 5)), rng.uniform(-math.pi, math.pi, (2, 5)))
    w.v[:], w.w[:] = rng.uniform(0, 1, (2, 5)), rng.uniform(-1, 1, (2, 5))
    o = w.observe()
    for e in range(2):
        for i in range(5):
            others = {j: (w.x[e, j], w.y[e, j], w.yaw[e, j], w.v[e, j], w.w[e, j], 0.0, None) for j in range(5) if j != i}
            ag = _agent_obs(i, (w.x[e, i], w.y[e, i], w.yaw[e, i]), (w.v[e, i], w.w[e, i]), (w.gx[e, i], w.gy[e, i]),
                            others, 0.0, np.zeros((0, 0)), D_COM, 5.0, 0.1)
            np.testing.assert_array_equal(o["gv"][e, i], goal_features(ag.d_g, ag.alpha_g, ag.v, ag.w))
            n = len(ag.neighbours)
            assert o["n_nb"][e, i] == n
            np.testing.assert_array_equal(o["nb"][e, i, :n], neighbour_features(ag.neighbours))
            assert not o["nb"][e, i, n:].any()


def test_vectorised_neighbour_polar_equals_the_scalar_view():
    rng = np.random.default_rng(3)
    x, y, yaw = rng.uniform(-10, 10, (6, 5)), rng.uniform(-10, 10, (6, 5)), rng.uniform(-4, 4, (6, 5))
    pol, n = neighbour_polar_array(x, y, yaw, 8.0)
    for e in range(6):
        for i in range(5):
            view = neighbour_view((x[e, i], y[e, i]), yaw[e, i],
                                  [(x[e, j], y[e, j], 0.0, 0.0, 0.0, 0.0, None) for j in range(5) if j != i], 8.0)
            assert n[e, i] == len(view.polar)
            np.testing.assert_allclose(pol[e, i, : n[e, i]], view.polar, rtol=0, atol=1e-14)  # arctan2: an ulp
    assert 0 < n.sum() < 6 * 5 * 4  # some in range, some not


def test_neighbour_view_predicts_at_most_one_second_and_keeps_the_reported_state():
    view = neighbour_view((0.0, 0.0), 0.0, [(1.0, 0.0, 0.0, 2.0, 0.3, 0.25, 4.0),  # 0.5 m ahead of its report
                                            (0.0, 5.0, -math.pi / 2, 1.0, 0.0, 2.5, None)], 10.0)  # capped at 1 s
    np.testing.assert_allclose(view.others, [(1.5, 0.0), (0.0, 4.0)], atol=1e-12)
    np.testing.assert_allclose(view.polar, [[4.0, math.pi / 2], [1.5, 0.0]])  # farthest first
    np.testing.assert_array_equal(view.states[0], [1.0, 0.0, 0.0, 2.0, 0.3, 0.25])
    assert view.d_goals[0] == 4.0 and math.isnan(view.d_goals[1])
    assert view.d_rmin == 1.5 and view.d_rmax == 4.0
