"""Deng's immune-network steering + position tracking (``--policy aina``), issue 6."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import SCENARIOS, run_fleet, scenario_dict, write_scenario

from stack.policies import Observation, make_policy
from stack.policies.aina import (Antigen, ImmuneNetwork, lobe, lyapunov_derivative, sectors, tracking_speed)
from stack.policies.aina import AinaConfig
from stack.scenario import ScenarioError, parse_scenario

SENSORS = np.radians(np.linspace(-78.75, 78.75, 8))  # eight sectors over a 180-degree lidar


def _wrapd(a: float) -> float:
    return (math.degrees(a) + 180.0) % 360.0 - 180.0


# --- eq. (7)-(8), (6), (10) on hand cases ---------------------------------------------------

def test_goal_affinities_eq_7_8_on_hand_cases():
    net = ImmuneNetwork(n_ab=4)  # antibodies at 0, 90, 180, 270 degrees
    ag = Antigen(theta_g=math.pi / 2, d_bar=np.ones(8), theta_S=SENSORS, theta_i=0.0)
    m = net.affinity(net.theta, ag)
    # F_goal1 = (1 + cos(theta_s - 0)) / 2 = 1, 0.5, 0, 0.5; F_goal2 = (1 + cos(theta_s - 90deg)) / 2 = 0.5, 1, 0.5, 0
    # m_s = 0.4 F_goal1 + 0.5 F_goal2 + 0.1 * 0 (no obstacle seen)
    assert m == pytest.approx([0.4 + 0.25, 0.2 + 0.5, 0.0 + 0.25, 0.2 + 0.0])
    assert lobe(np.array([0.0, math.pi / 3, math.pi]), 0.0) == pytest.approx([1.0, 0.75, 0.0])
    leader = Antigen(theta_g=math.pi, d_bar=np.ones(8), theta_S=SENSORS)  # eq. (10): mu1 F_goal
    assert net.affinity(net.theta, leader) == pytest.approx([0.0, 0.25, 0.5, 0.25])


def test_obstacle_term_is_a_repulsion_around_the_sensor():
    net = ImmuneNetwork(n_ab=36)
    free = Antigen(theta_g=0.0, d_bar=np.ones(8), theta_S=SENSORS)
    assert np.all(net.F_obs(net.theta, free) == 0.0)  # a sensor that sees nothing adds nothing
    d = np.ones(8)
    d[5] = 0.2
    F = net.F_obs(net.theta, Antigen(theta_g=0.0, d_bar=d, theta_S=SENSORS))
    assert F.max() <= 0.0
    assert net.theta[np.argmin(F)] == pytest.approx(SENSORS[5], abs=math.radians(5.1))
    nearer = d.copy()
    nearer[5] = 0.1
    assert net.F_obs(net.theta, Antigen(theta_g=0.0, d_bar=nearer, theta_S=SENSORS)).min() < F.min()
    # 90 degrees away from the sensor the lobe has vanished
    far = int(np.argmin(np.abs(np.angle(np.exp(1j * (net.theta - SENSORS[5] - math.pi / 2))))))
    assert abs(F[far]) < 1e-3 * abs(F.min())


# --- the network's choice -------------------------------------------------------------------

def test_open_space_steers_between_leader_heading_and_virtual_robot():
    net = ImmuneNetwork(rng=np.random.default_rng(1))
    ag = Antigen(theta_g=math.radians(90), d_bar=np.ones(8), theta_S=SENSORS, theta_i=0.0)
    th = [net.step(ag) for _ in range(5)][-1]
    # tau2 > tau1: closer to the virtual robot's azimuth than to the leader's heading, and between them
    assert 45.0 <= math.degrees(th) <= 90.0


@pytest.mark.parametrize("blocked", [3, 4, 2])
def test_network_picks_the_free_direction_when_a_sector_is_blocked(blocked):
    """A scan with an obstacle filling one sector: the chosen direction leaves that sector and stays
    within 60 degrees of the goal; with the sector free the network goes straight to the goal."""
    beams, fov = 180, math.pi
    ang = np.linspace(-fov / 2, fov / 2, beams)
    ranges = np.full(beams, 5.0)
    ranges[(ang >= SENSORS[blocked] - math.radians(11.25)) & (ang <= SENSORS[blocked] + math.radians(11.25))] = 1.2
    d_bar, centres = sectors(ranges, fov, 8, radius=0.5, d_max=4.5)
    assert np.argmin(d_bar) == blocked and d_bar[blocked] == pytest.approx(0.7 / 4.5)
    goal = float(SENSORS[blocked])  # the goal lies right behind the obstacle
    net = ImmuneNetwork(rng=np.random.default_rng(0))
    th = [net.step(Antigen(theta_g=goal, d_bar=d_bar, theta_S=centres)) for _ in range(5)][-1]
    off = abs(_wrapd(th - goal))
    assert 11.25 < off <= 60.0, off
    net.reset()
    th_free = [net.step(Antigen(theta_g=goal, d_bar=np.ones(8), theta_S=centres)) for _ in range(5)][-1]
    assert abs(_wrapd(th_free - goal)) <= 5.0


def test_neighbours_are_obstacles_only_within_the_detection_radius():
    beams, fov = 180, math.pi
    ranges = np.full(beams, 5.0)
    ranges[85:95] = 1.0  # a robot 1 m ahead
    nb = np.array([[1.4, 0.0]])  # its centre, as the radio delivered it
    d_far, _ = sectors(ranges, fov, 8, radius=0.3, d_max=4.7, neighbours=nb, robot_detect=0.5)
    assert d_far.min() == 1.0  # 0.7 m of clearance > 0.5 m: not an obstacle
    d_near, _ = sectors(ranges, fov, 8, radius=0.3, d_max=4.7, neighbours=nb, robot_detect=1.4)
    assert d_near.min() == pytest.approx(0.5)
    d_unknown, _ = sectors(ranges, fov, 8, radius=0.3, d_max=4.7)  # unknown body: an obstacle at full range
    assert d_unknown.min() == pytest.approx(0.7 / 4.7)


def test_algorithm_1_makes_new_antibodies_and_is_seeded():
    ag = Antigen(theta_g=0.3, d_bar=np.ones(8), theta_S=SENSORS, theta_i=0.1)
    a = ImmuneNetwork(rng=np.random.default_rng(7))
    b = ImmuneNetwork(rng=np.random.default_rng(7))
    ra = [a.step(ag) for _ in range(10)]
    assert ra == [b.step(ag) for _ in range(10)]
    assert len(a.last_offspring) >= a.clones
    grid = set(np.round(a.theta, 9))
    assert any(round(x, 9) not in grid for x in a.last_offspring)  # crossover/mutation leave the grid


# --- position tracking eq. (11)-(13) and the Lyapunov derivative of section 4.2 --------------

def test_tracking_speed_eq_13_and_bounds():
    # unbounded case: v_j = v_i cos(theta_i - theta_j) + K1 e_x - K2 e_y
    assert tracking_speed(0.5, 0.2, 0.1, 0.0, 0.0, K1=0.3, K2=0.08, V_max=0.5, dt=0.1) == pytest.approx(0.1 + 0.15 - 0.016)
    assert tracking_speed(5.0, 0.0, 0.1, 0.0, 0.0, K1=0.3, K2=0.08, V_max=0.5, dt=0.1) == 0.5  # V_max
    assert tracking_speed(0.01, 0.0, 0.0, 0.0, 0.0, K1=30.0, K2=0.08, V_max=0.5, dt=0.1) == pytest.approx(0.1)  # dist/t
    assert tracking_speed(-1.0, 0.0, 0.1, 0.0, 0.0, K1=0.3, K2=0.08, V_max=0.5, dt=0.1) == 0.0  # no reversing


@pytest.mark.parametrize("seed", range(4))
def test_lyapunov_derivative_is_non_positive_along_tracking_runs(seed):
    """A unicycle follower driven by the policy tracks the slot of a leader on a curved course;
    section 4.2's dV/dt, evaluated with the eq. (13) speed the policy computed, is <= 0 at every
    step, and the tracking error shrinks."""
    rng = np.random.default_rng(seed)
    cfg = AinaConfig()
    pol = make_policy("aina", _robot(cfg), seed=seed)
    dt, L, psi = 0.1, 1.0, math.radians(rng.uniform(90, 270))
    lx, ly, lyaw, v_i = 0.0, 0.0, 0.0, 0.1
    x, y = lx + rng.uniform(-2, 2), ly + rng.uniform(-2, 2)
    yaw = rng.uniform(-math.pi / 2, math.pi / 2)
    errors, vdots = [], []
    for k in range(600):
        w_i = 0.05 * math.sin(0.02 * k)
        sx, sy = lx + L * math.cos(psi), ly + L * math.sin(psi)
        d, a = math.hypot(sx - x, sy - y), math.atan2(sy - y, sx - x) - yaw
        obs = Observation(d_g=d, alpha_g=math.atan2(math.sin(a), math.cos(a)), v=0.0, w=0.0,
                          scans=np.full((1, 180), 5.0), goal_velocity=(v_i * math.cos(lyaw), v_i * math.sin(lyaw)),
                          yaw=yaw, dt=dt, target_yaw=lyaw)
        v, w = pol.act(obs)
        last = pol.last
        vdots.append(lyapunov_derivative(last["e_x"], last["e_y"], v_i, lyaw, yaw, last["v_13"], cfg.k1, cfg.k2))
        errors.append(d)
        w = max(-2.0, min(2.0, w))
        x, y, yaw = x + v * math.cos(yaw) * dt, y + v * math.sin(yaw) * dt, yaw + w * dt
        lx, ly, lyaw = lx + v_i * math.cos(lyaw) * dt, ly + v_i * math.sin(lyaw) * dt, lyaw + w_i * dt
    assert max(vdots) <= 1e-12, max(vdots)
    assert errors[-1] < 0.1 and errors[-1] < 0.2 * errors[0], (errors[0], errors[-1])


def _robot(cfg, role="follower"):
    sc = parse_scenario(scenario_dict())
    from dataclasses import replace

    return replace(sc.robot(1).with_config("aina", cfg), role=role, v_max=0.5)


# --- scenario keys ----------------------------------------------------------------------------

def test_aina_settings_are_checked():
    d = scenario_dict()
    d["robot"]["aina"] = {"tau1": 0.5, "tau2": 0.5, "tau3": 0.1}
    with pytest.raises(ScenarioError, match=r"robot.aina: tau1 \+ tau2 \+ tau3 must be 1"):
        parse_scenario(d, "s.yaml")
    d["robot"]["aina"] = {"n_ab": 0}
    with pytest.raises(ScenarioError, match=r"robot.aina.n_ab"):
        parse_scenario(d, "s.yaml")
    d["robot"]["aina"] = {"tau": 1}
    with pytest.raises(ScenarioError, match=r"robot.aina.tau: unknown field"):
        parse_scenario(d, "s.yaml")
    d["robot"]["aina"] = {"n_ab": 72, "v_leader": 0.3}
    assert parse_scenario(d).robot(0).config_for("aina").n_ab == 72


@pytest.mark.fleet
# --- in the fleet -----------------------------------------------------------------------------

def test_deng_switching_followers_take_the_line_after_the_switch(tmp_path):
    proc, rep = run_fleet(SCENARIOS / "deng-switching.yaml", tmp_path / "sw")
    assert rep is not None and proc.returncode == 0, (proc.stdout, proc.stderr)
    assert rep["formation_switches_s"] == [5.0]
    assert rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    for rid in ("1", "2"):
        conv = rep["robots"][rid]["error_convergence_time_s"]
        assert conv["x"] is not None and 5.0 < conv["x"] < 20.0, conv  # errors jump at the switch, then converge
        assert conv["y"] is not None and 5.0 < conv["y"] < 20.0, conv
        assert rep["robots"][rid]["final_error_m"] < 0.05
    assert (tmp_path / "sw" / "errors.png").stat().st_size > 10_000


@pytest.mark.fleet
def test_deng_obstacles_no_collisions_and_the_formation_recovers(tmp_path):
    proc, rep = run_fleet(SCENARIOS / "deng-obstacles.yaml", tmp_path / "ob", "--no-plots")
    assert rep is not None and proc.returncode == 0, (proc.stdout, proc.stderr)
    assert rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    assert rep["obstacles_cleared_at_s"] is not None and rep["formation_recovery_s"] is not None
    assert rep["formation_recovery_s"] <= 10.0


@pytest.mark.fleet
def test_aina_takes_the_obstacle_field_with_noisy_odometry_and_fixes(tmp_path):
    """Issues 4 and 6: four-robot-obstacles with odometry noise 0.05/0.05 and 1 Hz fixes of 0.3 m:
    success, zero collisions, estimator RMSE < 0.2 m. (The 0.1 m recovery bound is checked on
    the noise-free Deng scenario: here each robot's own estimate is off by about 0.12 m RMS.)"""
    import yaml

    d = yaml.safe_load((SCENARIOS / "four-robot-obstacles.yaml").read_text())
    d["robot"]["odom_noise"] = {"v_std": 0.05, "w_std": 0.05}
    d["robot"]["fix"] = {"rate_hz": 1.0, "std": 0.3}
    path = write_scenario(tmp_path / "obstacles-noisy.yaml", d)
    proc, rep = run_fleet(path, tmp_path / "fo", "--policy", "aina", "--no-plots")
    assert rep is not None and proc.returncode == 0, (proc.stdout, proc.stderr)
    assert rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    assert max(r["estimator_rmse_m"] for r in rep["robots"].values()) < 0.2
    assert rep["formation_error_rms_m"] < 0.6
    assert rep["min_robot_distance_m"] >= 2 * 0.5
