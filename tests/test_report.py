"""build_report and its metrics, in process, on hand-made ground-truth logs whose answers are known.

The formation scenario: leader 0 drives along y = 0 at 1 m/s from x = 0.25 towards the goal (10, 0);
follower 1's slot is 2 m behind it (psi 180 deg), follower 2's 2 m to its left (psi 90 deg); dt 0.1 s.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import scenario_dict

from stack.agents.timing import LatencyHistogram
from stack.comm.messages import Diag
from stack.fleet import metrics as m
from stack.fleet.report import build_report, report_of
from stack.fleet.truth import TruthLog, targets
from stack.scenario import parse_scenario

DT = 0.1


def formation_scenario(duration: float = 10.0, obstacles: list | None = None, comm_range: float = 5.0):
    d = scenario_dict(duration=duration, world={"obstacles": obstacles or []},
                      formation={"leader": 0, "goal": [10.0, 0.0],
                                 "slots": {1: {"L": 2.0, "psi_deg": 180}, 2: {"L": 2.0, "psi_deg": 90}}},
                      robots=[{"id": 0, "role": "leader", "pose": [0.25, 0.0, 0.0]},
                              {"id": 1, "role": "follower", "pose": [-1.75, 0.0, 0.0]},
                              {"id": 2, "role": "follower", "pose": [0.25, 2.0, 0.0]}],
                      success={"goal_tolerance": 0.5, "max_time": duration, "no_collisions": True})
    d["robot"] = dict(d["robot"], comm_range=comm_range)
    return parse_scenario(d)


def formation_log(K: int = 101) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, x, y) of the perfect formation: every follower on its slot at every step."""
    t = np.arange(K) * DT
    lead = 0.25 + t
    x = np.column_stack([lead, lead - 2.0, lead])
    y = np.column_stack([np.zeros(K), np.zeros(K), np.full(K, 2.0)])
    return t, x, y


def report(sc, log, *, faults=(), diags=None, estimates=None, world=None, crashed=()):
    tg = targets(sc, log, m.frozen_mask(list(faults), log.t, log.ids))
    return report_of(sc, log, tg, world or {}, diags=diags or {}, estimates=estimates or {}, faults=list(faults),
                     crashed=list(crashed), wall_time_s=1.0, realtime=False)


# --- the whole report ----------------------------------------------------------------------------

def test_perfect_formation_reaches_the_goal():
    sc = formation_scenario()
    t, x, y = formation_log()
    rep = report(sc, TruthLog.of([0, 1, 2], t, x, y))
    assert rep["success"] is True
    assert rep["leader_time_to_goal_s"] == 9.3  # first step with x >= 9.5 (0.5 m tolerance): t = 9.3
    assert rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    assert rep["min_robot_distance_m"] == 2.0 and rep["max_robot_distance_m"] == round(math.sqrt(8), 4)
    assert rep["min_obstacle_distance_m"] is None
    assert rep["connectivity"] == 1.0 and rep["formation_error_rms_m"] == 0.0
    assert rep["arrival_spread_steps"] is None and rep["sim_time_s"] == 10.0 and rep["steps"] == 101
    r1 = rep["robots"]["1"]
    assert r1["role"] == "follower" and r1["path_length_m"] == 10.0 and r1["final_error_m"] == 0.0
    assert r1["error_convergence_time_s"] == {"x": 0.0, "y": 0.0}
    assert r1["arrival_time_s"] == 9.3  # its final slot placed around the goal is (8, 0)
    assert rep["robots"]["0"]["final_error_m"] == 0.25  # the leader's error is to the goal
    assert rep["robots"]["0"]["situations"] == {} and rep["robots"]["0"]["fixes"] is None  # no diag heard


def test_a_collision_at_a_known_step_is_counted_once_per_entry():
    sc = formation_scenario()
    t, x, y = formation_log()
    x[40:45, 1] = x[40:45, 0] - 0.8  # follower 1 rams the leader at steps 40-44 ...
    x[60:62, 1] = x[60:62, 0] - 0.9  # ... and again at 60-61
    rep = report(sc, TruthLog.of([0, 1, 2], t, x, y))
    assert rep["collisions"] == {"robot_robot": 2, "robot_obstacle": 0}
    assert rep["min_robot_distance_m"] == 0.8
    assert rep["success"] is False  # no_collisions
    assert rep["robots"]["1"]["error_convergence_time_s"]["x"] == 6.2  # after the last contact, step 62


def test_a_follower_converging_at_a_known_time():
    sc = formation_scenario()
    t, x, y = formation_log()
    ex = np.maximum(0.0, 1.0 - t / 3.0)  # follower 1 starts 1 m short of its slot, closes it in 3 s
    x[:, 1] -= ex
    rep = report(sc, TruthLog.of([0, 1, 2], t, x, y))
    r1 = rep["robots"]["1"]
    assert r1["error_convergence_time_s"] == {"x": 2.9, "y": 0.0}  # 1 - 2.8/3 = 0.067 >= 0.05 > 1 - 2.9/3
    assert r1["final_error_m"] == 0.0
    # RMS over both followers and every step; follower 2 is exact
    assert rep["formation_error_rms_m"] == round(math.sqrt((ex ** 2).sum() / (2 * len(t))), 4)


def test_a_follower_that_never_converges():
    sc = formation_scenario()
    t, x, y = formation_log()
    y[:, 2] += 0.5
    rep = report(sc, TruthLog.of([0, 1, 2], t, x, y))
    assert rep["robots"]["2"]["error_convergence_time_s"] == {"x": 0.0, "y": None}
    assert rep["robots"]["2"]["final_error_m"] == 0.5
    assert rep["formation_error_rms_m"] == round(math.sqrt(0.25 / 2), 4)
    assert rep["robots"]["2"]["arrival_time_s"] is None  # always 0.5 m off the slot: never within < 0.5 ... at 0.5
    assert rep["success"] is True  # success judges the leader


def test_connectivity_counts_the_steps_with_a_follower_out_of_range():
    sc = formation_scenario(comm_range=5.0)
    t, x, y = formation_log()
    y[20:30, 2] = 6.0  # 6 m from the leader for 10 of 101 steps
    rep = report(sc, TruthLog.of([0, 1, 2], t, x, y))
    assert rep["connectivity"] == round(91 / 101, 4)


def test_the_leader_killed_mid_run():
    """Leader 0 dies at t = 5 and its body stays where it stopped; robot 1 (lowest live id) takes over and
    robot 2 keeps its place in the shape, now (2, 2) from robot 1. Robot 1 runs through the dead body."""
    sc = formation_scenario(duration=13.0)
    t, x, y = formation_log(K=131)
    alive = np.ones(x.shape, bool)
    alive[50:, 0] = False
    x[50:, 0] = x[49, 0]
    faults = [{"robot": 0, "kind": "killed", "at_s": 5.0, "sim_time_s": 5.0, "step": 50}]
    diags = {1: Diag(id=1, stamp=0.0, step=130, state="stopped", noticed={0: 5.3}, led_since=5.4),
             2: Diag(id=2, stamp=0.0, step=130, state="stopped", noticed={0: 5.2})}
    rep = report(sc, TruthLog.of([0, 1, 2], t, x, y, alive=alive), faults=faults, diags=diags)
    assert rep["leader_time_to_goal_s"] == 11.3  # robot 1 at x >= 9.5: t - 1.75 >= 9.5
    assert rep["collisions"]["robot_robot"] == 1 and rep["min_robot_distance_m"] < 0.1  # the body is there
    assert rep["max_robot_distance_m"] == round(math.sqrt(8), 4)  # the dead one is out of the spread
    assert rep["formation_error_rms_m"] == 0.0  # robot 2 is on its new slot throughout
    assert rep["robots"]["0"]["alive_at_end"] is False and rep["robots"]["1"]["alive_at_end"] is True
    assert rep["robots"]["0"]["final_error_m"] == 4.85  # at its last step with a target, t = 4.9
    assert rep["robots"]["1"]["led_since_s"] == 5.4
    (kill,) = rep["faults"]
    assert kill["noticed_s"] == {"1": 0.3, "2": 0.2}
    assert kill["new_leader"] == 1 and kill["takeover_s"] == 0.4
    assert rep["success"] is False  # the run-over body


def test_a_frozen_follower_is_out_of_the_formation_until_restarted():
    sc = formation_scenario()
    t, x, y = formation_log()
    y[50:, 2] = 3.0  # frozen at t = 5: it stands 1 m off its slot
    frozen = [{"robot": 2, "kind": "frozen", "sim_time_s": 5.0}]
    log = TruthLog.of([0, 1, 2], t, x, y)
    assert report(sc, log, faults=frozen)["formation_error_rms_m"] == 0.0
    restarted = frozen + [{"robot": 2, "kind": "restarted", "sim_time_s": 8.0}]  # back in from step 80
    # 21 steps 1 m off, over 101 + 71 follower-steps (steps 50-79 of robot 2 do not count)
    assert report(sc, log, faults=restarted)["formation_error_rms_m"] == round(math.sqrt(21 / 172), 4)
    assert report(sc, log)["formation_error_rms_m"] == round(math.sqrt(51 / (2 * 101)), 4)


def arrival_scenario():
    d = scenario_dict(duration=10.0, world={"obstacles": []}, coordination="arrival_time",
                      robots=[{"id": 0, "pose": [0.0, 0.0, 0.0], "goal": [10.0, 0.0]},
                              {"id": 1, "pose": [0.0, 0.0, 0.0], "goal": [0.0, 10.0]},
                              {"id": 2, "pose": [0.0, 0.0, 0.0], "goal": [-10.0, 0.0]}],
                      success={"goal_tolerance": 0.5, "max_time": 10.0, "no_collisions": True})
    del d["formation"]
    return parse_scenario(d)


def arrival_log(arrive_at=(5.0, 5.3, 5.7)) -> TruthLog:
    """Each peer comes in from afar along its own axis at 1.2 m/s and stops at its goal at ``arrive_at``."""
    t = np.arange(101) * DT
    goals = np.array([[10.0, 0.0], [0.0, 10.0], [-10.0, 0.0]])
    rest = np.maximum(0.0, np.array(arrive_at)[None, :] - t[:, None]) * 1.2  # (K, 3) distance still to go
    x = goals[None, :, 0] * (1 + rest / 10.0)
    y = goals[None, :, 1] * (1 + rest / 10.0)
    return TruthLog.of([0, 1, 2], t, x, y)


def test_an_arrival_time_task():
    sc = arrival_scenario()
    rep = report(sc, arrival_log())
    # within 0.5 m when arrive_at - t <= 0.42: the step 0.4 s before each arrival
    assert [rep["robots"][str(i)]["arrival_time_s"] for i in range(3)] == [4.6, 4.9, 5.3]
    assert rep["arrival_spread_steps"] == 7
    assert rep["robots"]["0"]["role"] == "peer" and rep["connectivity"] is None
    assert rep["leader_time_to_goal_s"] is None and rep["formation_error_rms_m"] is None
    assert rep["robots"]["2"]["error_convergence_time_s"] == {"x": 5.7, "y": 0.0}  # to its goal
    assert rep["success"] is True
    assert report(sc, arrival_log(), crashed=[{"process": "agent 1"}])["success"] is False
    late = report(sc, arrival_log((5.0, 5.3, 11.0)))
    assert late["robots"]["2"]["arrival_time_s"] is None and late["arrival_spread_steps"] is None
    assert late["success"] is False


def test_an_arrival_task_with_a_peer_killed():
    sc = arrival_scenario()
    log = arrival_log((5.0, 5.3, 11.0))
    alive = np.ones(log.x.shape, bool)
    alive[30:, 2] = False
    log = TruthLog.of(log.ids, log.t, log.x, log.y, alive=alive)
    rep = report(sc, log)
    assert rep["success"] is True  # the live peers arrived; the dead one is not waited for
    assert rep["arrival_spread_steps"] is None


# --- metrics one by one ---------------------------------------------------------------------------

def test_entries_and_convergence():
    assert m.entries(np.array([True, True, False, True, False, False, True])) == 3
    assert m.entries(np.zeros((4, 3), bool)) == 0
    t = np.arange(5) * 1.0
    assert m.converged_since(t, np.array([1.0, 0.5, 0.01, 0.0, 0.02]), 0.05) == 2.0
    assert m.converged_since(t, np.array([0.0, 0.0, 0.0, 0.0, 0.1]), 0.05) is None
    assert m.converged_since(t, np.zeros(5), 0.05) == 0.0
    assert m.rounded(float("inf")) is None and m.rounded(float("nan")) is None and m.rounded(1.23456) == 1.2346


def test_obstacle_clearance_collisions_and_recovery():
    sc = formation_scenario(obstacles=[{"type": "cylinder", "x": 5.0, "y": 3.0, "radius": 0.5}])
    t, x, y = formation_log()
    y[t < 7.5, 1] += 0.3  # follower 1 is 0.3 m off its slot until 7.5 s, then 0.05 m
    y[t >= 7.5, 1] += 0.05
    log = TruthLog.of([0, 1, 2], t, x, y)
    clear = m.clearance(sc, log)
    assert clear[:, 2].min() == pytest.approx(np.hypot(x[:, 2] - 5.0, 1.0).min() - 0.5)
    assert m.collisions(sc, log, clear) == {"robot_robot": 0, "robot_obstacle": 0}
    # robot 2 (2 m left of the leader) passes 1 m beside the cylinder: near (clearance - radius < 1 m)
    # while |x - 5| < sqrt(3), so for the last time at t = 6.4
    assert m.obstacle_recovery(sc, log, targets(sc, log, np.zeros(x.shape, bool)), clear) == pytest.approx((6.4, 1.1))
    y[45:50, 2] = 3.0  # now it runs into the cylinder for five steps (x 4.75 .. 5.15)
    log = TruthLog.of([0, 1, 2], t, x, y)
    assert m.collisions(sc, log, m.clearance(sc, log))["robot_obstacle"] == 1


def test_estimator_rmse():
    t, x, y = formation_log(K=11)
    log = TruthLog.of([0, 1, 2], t, x, y)
    est = [(2, x[2, 1] + 0.3, y[2, 1] + 0.4), (5, x[5, 1], y[5, 1]), (99, 0.0, 0.0), (-1, 0.0, 0.0)]  # bad steps skipped
    assert m.estimator_rmse(log, 1, est) == pytest.approx(math.sqrt(0.25 / 2))
    assert m.estimator_rmse(log, 1, []) is None
    assert m.estimator_rmse(log, 1, [(50, 0.0, 0.0)]) is None


def test_comm_totals_and_latency_percentiles():
    diags = {1: Diag(id=1, stamp=0, step=0, state="stopped", sent=10, received=20, delivered=18, dropped_loss=1,
                     dropped_range=1, malformed=2, loop_hist={10: 3}, state_latency_hist={5: 1}),
             2: Diag(id=2, stamp=0, step=0, state="stopped", sent=10, received=20, delivered=20, loop_hist={20: 1})}
    assert m.comm_totals(diags, {"malformed": 4}) == {"sent": 40, "received": 40, "delivered": 38, "dropped_loss": 1,
                                                      "dropped_range": 1, "malformed": 6, "broadcasts": 20}
    loop = m.latency_percentiles(diags, "loop_hist")
    assert loop == {"p50": round(LatencyHistogram.upper_ms(10), 4), "p99": round(LatencyHistogram.upper_ms(20), 4),
                    "samples": 4}
    assert m.latency_percentiles({}, "loop_hist") == {"p50": None, "p99": None, "samples": 0}


def test_device_fault_stopped_after():
    t, x, y = formation_log(K=51)
    v = np.ones(x.shape)
    v[35:, 1] = 0.01  # robot 1 stands still from t = 3.5
    log = TruthLog.of([0, 1, 2], t, x, y, v=v)
    world = {"events": [{"event": "device fault", "robot": 1, "t": 3.0, "what": "heartbeats stop"},
                        {"event": "killed", "robot": 2, "t": 1.0}]}
    diags = {1: Diag(id=1, stamp=0, step=0, state="fault", fault="can driver: no heartbeat")}
    (f,) = m.device_faults(world, diags, log)
    assert f == {"robot": 1, "kind": "device_fault", "what": "heartbeats stop", "sim_time_s": 3.0,
                 "driver_fault": "can driver: no heartbeat", "stopped_s": 0.5}
    v[:, 1] = 1.0  # never stops
    assert m.device_faults(world, {}, TruthLog.of([0, 1, 2], t, x, y, v=v))[0]["stopped_s"] is None


def test_a_killed_follower_has_no_takeover():
    sc = formation_scenario()
    faults = [{"robot": 2, "kind": "killed", "sim_time_s": 4.0},
              {"robot": 1, "kind": "crashed", "sim_time_s": 6.0, "exit_code": 1}]
    diags = {0: Diag(id=0, stamp=0, step=0, state="stopped", noticed={2: 4.5, 1: 5.9}, led_since=0.0)}
    kill, crash = m.fault_details(faults, diags, sc.formation)
    assert kill["noticed_s"] == {"0": 0.5} and "new_leader" not in kill
    assert crash["noticed_s"] == {}  # noticed before the crash: not this fault's


# --- the files ------------------------------------------------------------------------------------

def test_build_report_reads_the_run_folder_and_writes_report_json(tmp_path):
    sc = formation_scenario()
    t, x, y = formation_log()
    K, N = x.shape
    np.savez_compressed(tmp_path / "truth.npz", ids=np.array([0, 1, 2]), t=t, x=x, y=y, yaw=np.zeros((K, N)),
                        v=np.ones((K, N)), w=np.zeros((K, N)), alive=np.ones((K, N), bool),
                        cmd_v=np.zeros((K, N)), cmd_w=np.zeros((K, N)))
    (tmp_path / "world.json").write_text(json.dumps({"end_reason": "duration", "steps_per_s": 123.456789,
                                                     "late_steps": 0, "malformed": 3}))
    rep = build_report(sc, tmp_path, diags={}, estimates={}, faults=[], crashed=[], wall_time_s=2.5, realtime=True,
                       plots=False)
    assert json.loads((tmp_path / "report.json").read_text()) == rep
    assert rep["mode"] == "realtime" and rep["end_reason"] == "duration" and rep["steps_per_s"] == 123.4568
    assert rep["comm"]["malformed"] == 3 and rep["late_steps"] == 0 and rep["wall_time_s"] == 2.5
    assert rep["success"] is True and rep["leader_time_to_goal_s"] == 9.3
    assert not list(tmp_path.glob("*.png"))


def test_build_report_without_a_world_log(tmp_path):
    sc = formation_scenario()
    crashed = [{"process": "router", "exit_code": 1, "sim_time_s": 0.0, "log_tail": "no"}]
    rep = build_report(sc, tmp_path, diags={}, estimates={}, faults=[], crashed=crashed, wall_time_s=0.5,
                       realtime=False)
    assert rep["end_reason"] == "no world log" and rep["success"] is False and rep["crashed"] == crashed
    assert json.loads((tmp_path / "report.json").read_text()) == rep


def test_build_report_plots(tmp_path):
    for name, sc, log in (("formation", formation_scenario(), TruthLog.of([0, 1, 2], *formation_log())),
                          ("arrival", arrival_scenario(), arrival_log())):
        out = tmp_path / name
        out.mkdir()
        np.savez_compressed(out / "truth.npz", ids=np.array(log.ids), t=log.t, x=log.x, y=log.y, v=log.v, alive=log.alive)
        build_report(sc, out, diags={}, estimates={}, faults=[], crashed=[], wall_time_s=1.0, realtime=False)
        # errors.png: the followers' slot errors, so only with a formation
        want = {"trajectories.png", "distances.png"} | ({"errors.png"} if name == "formation" else set())
        assert {p.name for p in out.glob("*.png")} == want
