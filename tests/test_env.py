"""The PettingZoo env of the training world (issue 19 item 5): API tests, the one observation builder,
and the chain env -> trained weights -> ``make_policy("drl", robot)`` -> a fleet."""

import math

import numpy as np
import pytest

from gymnasium.utils.env_checker import check_env  # the `test` extra: pettingzoo, gymnasium
from pettingzoo.test import parallel_api_test, parallel_seed_test

from stack.policies.drl.observation import ACTIONS, N_ACTIONS
from stack.policies.drl.reward import reward
from stack.scenario import load_scenario, parse_scenario
from stack.train.env import STAND, EnvConfig, FormationEnv, FormationParallelEnv, network_inputs

from conftest import ROOT, run_fleet, scenario_dict, write_scenario

DIAMOND = ROOT / "scenarios" / "four-robot-diamond.yaml"


def test_parallel_api_and_seed_tests_pass():
    parallel_api_test(FormationParallelEnv(scenario=DIAMOND), num_cycles=40)
    parallel_api_test(FormationParallelEnv(robots=1, max_steps=30), num_cycles=40)
    parallel_seed_test(lambda: FormationParallelEnv(robots=3, max_steps=30), num_cycles=30)


def test_gymnasium_single_robot_view_passes_check_env():
    check_env(FormationEnv(robots=1, max_steps=30), skip_render_check=True)
    env = FormationEnv(scenario=DIAMOND, robot=2)
    check_env(env, skip_render_check=True)
    assert env.me == "robot_2" and env.action_space.n == N_ACTIONS == 15
    with pytest.raises(ValueError, match="robot: expected 0..3"):
        FormationEnv(scenario=DIAMOND, robot=4)


def test_a_scenario_gives_the_agents_targets_and_obstacles():
    env = FormationParallelEnv(scenario=DIAMOND)
    obs, _ = env.reset(seed=1)
    sc = load_scenario(DIAMOND)
    assert env.agents == ["robot_0", "robot_1", "robot_2", "robot_3"]
    w = env.world
    assert (w.gx[0, 0], w.gy[0, 0]) == sc.formation.goal
    assert math.isclose(w.gx[0, 2], 35.0 - 4.0) and abs(w.gy[0, 2]) < 1e-9  # slot 2: L 4 m, psi 180 deg, eq. (3)
    assert np.allclose(w.x[0], [r.pose[0] for r in sc.robots]) and w.cfg.max_steps == 1200
    assert (w.circles[0, :, 2] > 0).sum() == 1 and (w.boxes[0, :, 2] > 0).sum() == 3  # a cylinder, a box, two walls
    for a in env.agents:
        assert env.observation_space(a).contains(obs[a])
        assert obs[a]["n_nb"] == 3  # everyone within 10 m


def test_observations_are_the_agents_and_match_the_training_worlds():
    """The env builds each robot's Observation (stack.models.observation) and normalises it as DrlPolicy does;
    the training world's vectorised observe() gives the same network inputs."""
    env = FormationParallelEnv(robots=4, noise_std=0.0)
    obs, _ = env.reset(seed=5)
    rng = np.random.default_rng(0)
    for _ in range(15):
        if not env.agents:
            break
        ref = env.world.observe()
        for a in env.agents:
            i = env._index[a]
            o = env.robot_observation(a)
            assert o.target == (env.world.gx[0, i], env.world.gy[0, i]) and o.neighbours.shape == (3, 2)
            assert np.allclose(obs[a]["scans"], ref["scans"][0, i], atol=1e-6)
            assert np.allclose(obs[a]["gv"], ref["gv"][0, i], atol=1e-6)
            assert obs[a]["n_nb"] == ref["n_nb"][0, i]
            assert np.allclose(obs[a]["nb"], ref["nb"][0, i], atol=1e-6)
            assert all(np.array_equal(network_inputs(o, 3)[k], obs[a][k]) for k in obs[a])
        obs, *_ = env.step({a: int(rng.integers(15)) for a in env.agents})


def test_rewards_are_eq_14_17_and_stopped_robots_leave():
    env = FormationParallelEnv(robots=1, noise_std=0.0, max_steps=500)
    env.reset(seed=2)
    w = env.world
    d0 = math.hypot(w.gx[0, 0] - w.x[0, 0], w.gy[0, 0] - w.y[0, 0])
    _, rew, term, trunc, info = env.step({"robot_0": 12})  # (v, w) = (1, 0)
    d1 = math.hypot(w.gx[0, 0] - w.x[0, 0], w.gy[0, 0] - w.y[0, 0])
    from stack.train.drlworld import obstacle_distance

    d_obs = obstacle_distance(w.x[0], w.y[0], w.circles[0], w.boxes[0])[0]
    r, _, _ = reward(d0, d1, math.inf, d_obs, np.zeros(2), ACTIONS[12])
    assert math.isclose(rew["robot_0"], float(r), rel_tol=1e-9) and ACTIONS[STAND].tolist() == [0.0, 0.0]
    steps = 1
    while env.agents:
        _, rew, term, trunc, info = env.step({"robot_0": 12})
        steps += 1
    assert term["robot_0"] or trunc["robot_0"]
    assert term["robot_0"] == (info["robot_0"]["arrived"] or info["robot_0"]["collided"])
    assert trunc["robot_0"] == (steps == 500 and not term["robot_0"])


def test_bad_settings_are_one_line_errors():
    with pytest.raises(TypeError, match="bogus"):
        EnvConfig(bogus=1)
    with pytest.raises(Exception, match="cannot read"):
        FormationParallelEnv(scenario="/nonexistent.yaml")


def test_train_save_load_and_act_through_the_agents_factory(tmp_path):
    """The chain in-process: a few learning steps on the env, the state_dict saved, loaded by make_policy("drl")
    from robot.drl.weights, acting on an Observation the env built; the same greedy action as the trained net."""
    import torch

    from stack.policies import make_policy
    from stack.train.envlearn import EnvLearnConfig, act, evaluate_on_env, train_on_env

    env = FormationParallelEnv(robots=2, max_steps=40)
    out = tmp_path / "w" / "drl.pt"
    s = train_on_env(env, EnvLearnConfig(steps=60, learn_start=32, batch=16, seed=3), out, log=lambda *_: None)
    assert out.exists() and s["updates"] > 0 and s["steps"] == 60
    d = scenario_dict()
    d["robot"]["drl"] = {"weights": str(out), "shield": False, "runtime": "torch"}  # the torch module itself
    robot = parse_scenario(d, "env.yaml").robots[1]
    policy = make_policy("drl", robot)
    state = torch.load(out, weights_only=True)
    assert all(torch.equal(policy.net.state_dict()[k], v) for k, v in state.items())
    obs, _ = env.reset(seed=9)
    o = env.robot_observation("robot_1")
    v, w = policy.act(o)
    a = act(policy.net, obs, ["robot_1"], 0.0, np.random.default_rng(0))["robot_1"]
    assert (v, w) == tuple(ACTIONS[a].tolist())
    ev = evaluate_on_env(policy.net, env, 1, 100)
    assert ev["robots"] == 2 and math.isclose(ev["arrived"] + ev["collided"] + ev["timeout"], 1.0)


@pytest.mark.fleet
def test_env_trained_weights_run_in_a_fleet(tmp_path):
    """A very short env training, the weights in a scenario copy's robot.drl.weights, `stack-fleet run --policy drl`."""
    import sys

    sys.path.insert(0, str(ROOT / "examples"))
    from train_env import scenario_with_weights

    from stack.train.envlearn import EnvLearnConfig, train_on_env

    weights = tmp_path / "drl.pt"
    init = ROOT / "stack" / "policies" / "drl" / "weights" / "drl.pt"
    train_on_env(FormationParallelEnv(robots=4, max_steps=40), EnvLearnConfig(steps=40, learn_start=16, batch=16, init=init,
                                                                               eps_start=0.05), weights, log=lambda *_: None)
    base = write_scenario(tmp_path / "short.yaml", scenario_dict())
    (tmp_path / "run").mkdir()
    sc = scenario_with_weights(base, weights, tmp_path / "run")
    assert load_scenario(sc).robots[0].config_for("drl").weights == str(weights.resolve())
    proc, rep = run_fleet(sc, tmp_path / "fleet", "--policy", "drl", "--no-plots")
    assert proc.returncode == 0 and rep is not None and rep["success"], proc.stderr[-2000:]
    assert set(rep["policies"].values()) == {"drl"} and rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}


def test_a_generated_course_is_an_env(tmp_path):
    """`stack-fleet generate` writes a scenario; the env plays it (every obstacle, every robot, the slots)."""
    from conftest import run_cli

    course = tmp_path / "course.yaml"
    proc = run_cli(["stack-fleet", "generate", "--seed", "3", "--robots", "6", "--density", "high", "--out", str(course)])
    assert proc.returncode == 0, proc.stderr
    sc = load_scenario(course)
    env = FormationParallelEnv(scenario=course)
    parallel_api_test(env, num_cycles=10)
    env.reset(seed=0)
    w = env.world
    n_c = sum(o.type == "cylinder" for o in sc.obstacles)
    assert env.possible_agents == [f"robot_{r.id}" for r in sc.robots] and w.R == 6
    assert (w.circles[0, :, 2] > 0).sum() == n_c and (w.boxes[0, :, 2] > 0).sum() == len(sc.obstacles) - n_c
    assert env.observation_space("robot_0")["nb"].shape == (5, 2)
