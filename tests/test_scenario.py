"""Scenario validation: every shipped scenario loads; bad input gives exit 2 and one line naming the field."""

from __future__ import annotations

import copy
import re

import pytest

from conftest import SCENARIOS, run_cli, scenario_dict, write_scenario
from stack.scenario import ScenarioError, load_scenario, parse_scenario, with_overrides


@pytest.mark.parametrize("path", sorted(SCENARIOS.glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_scenarios_load(path):
    sc = load_scenario(path)
    assert sc.robots and sc.dt > 0
    if sc.formation:
        assert set(sc.formation.slots) == {r.id for r in sc.robots} - {sc.formation.leader}


def _bad(mutate):
    d = scenario_dict()
    mutate(d)
    return d


BAD = [
    (lambda d: d["robots"][2].__setitem__("pose", [1.0, 2.0]), "robots[2].pose: expected 3 numbers, got 2"),
    (lambda d: d.__setitem__("dt", -0.1), "dt: must be > 0"),
    (lambda d: d.__setitem__("speed", 3), "speed: unknown field"),
    (lambda d: d["robot"].__setitem__("radius", "big"), "robot.radius: expected a number, got text ('big')"),
    (lambda d: d["robot"]["lidar"].__setitem__("beams", 0), "robot.lidar.beams: must be >= 1"),
    (lambda d: d["robot"]["lidar"].__setitem__("fov", 180), "robot.lidar.fov: unknown field"),
    (lambda d: d["comm"].__setitem__("loss", 1.5), "comm.loss: must be <= 1"),
    (lambda d: d["comm"].__setitem__("burst", {"p_good_bad": 0.1}), "comm.burst.p_bad_good: missing"),
    (lambda d: d["world"]["obstacles"].append({"type": "sphere", "x": 1}), "world.obstacles[3].type: expected one of cylinder, box, wall"),
    (lambda d: d["world"]["obstacles"][0].pop("radius"), "world.obstacles[0].radius: missing"),
    (lambda d: d["formation"]["slots"].pop(2), "formation.slots: follower 2 has no slot"),
    (lambda d: d["formation"].__setitem__("leader", 9), "formation.leader: no robot with id 9"),
    (lambda d: d["robots"][1].__setitem__("policy", "magic"), "robots[1].policy: expected one of pid, drl"),
    (lambda d: d["formation"].__setitem__("schedule", {"at": 1}), "formation.schedule: expected a list of {at, slots}"),
    (lambda d: d["formation"].__setitem__("schedule", [{"at": 1.0}]), "formation.schedule[0].slots: missing"),
    (lambda d: d["formation"].__setitem__("schedule", [{"at": 99.0, "slots": {1: {"L": 1, "psi_deg": 0}}}]),
     "formation.schedule[0].at: must be <= 25"),
    (lambda d: d["formation"].__setitem__("schedule", [{"at": 5.0, "slots": {1: {"L": 1, "psi_deg": 0}}},
                                                       {"at": 5.0, "slots": {2: {"L": 1, "psi_deg": 0}}}]),
     "formation.schedule[1].at: must be later than the previous change (5 s), got 5"),
    (lambda d: d["formation"].__setitem__("schedule", [{"at": 5.0, "slots": {0: {"L": 1, "psi_deg": 0}}}]),
     "formation.schedule[0].slots.0: the leader has no slot"),
    (lambda d: d["formation"].__setitem__("schedule", [{"at": 5.0, "slots": {}}]),
     "formation.schedule[0].slots: empty"),
    (lambda d: d["formation"].__setitem__("schedule", [{"at": 5.0, "slots": {3: {"L": 1}}}]),
     "formation.schedule[0].slots.3.psi_deg: missing"),
    (lambda d: d["robots"][1].__setitem__("driver", "ros"), "robots[1].driver: expected one of sim, can"),
    (lambda d: d["robots"][3].__setitem__("id", 1), "robots[3].id: duplicate id 1"),
    (lambda d: d["robots"][0].__setitem__("role", "follower"), "robots[0].role: robot 0 is follower but formation.leader is 0"),
    (lambda d: d.__setitem__("robots", []), "robots: expected a non-empty list"),
    (lambda d: d.pop("formation"), "formation: missing"),
    (lambda d: d["success"].__setitem__("no_collisions", "yes"), "success.no_collisions: expected true or false"),
    (lambda d: d["success"].__setitem__("settle_s", -1), "success.settle_s: must be >= 0, got -1"),
    (lambda d: d["robot"].__setitem__("drl", {"shields": True}), "robot.drl.shields: unknown field"),
    (lambda d: d["robot"].__setitem__("drl", {"shield": "yes"}), "robot.drl.shield: expected true or false, got text ('yes')"),
    (lambda d: d["robots"][1].__setitem__("drl", {"weights": "nope.pt"}), "robots[1].drl.weights: no such file: nope.pt"),
    (lambda d: d["robots"][2].__setitem__("qlearn", {"cell": -0.5}), "robots[2].qlearn.cell: must be > 0, got -0.5"),
    (lambda d: d["robot"].__setitem__("pid", {"v_cruise": 1.5}), "robot.pid.v_cruise: must be <= 1, got 1.5"),
    (lambda d: d["robot"].__setitem__("fuzzy", {"coordinator": "central"}),
     "robot.fuzzy.coordinator: expected one of flc, lstm, none, got 'central'"),
    (lambda d: d["robot"].__setitem__("fuzzy", {"target": [1, "x"]}), "robot.fuzzy.target[1]: expected a number, got text ('x')"),
    (lambda d: d["robot"].__setitem__("sim", {"port": 1}), "robot.sim.port: unknown field (allowed: none)"),
    (lambda d: d["robots"][1].__setitem__("guard", {"margin": -1}), "robots[1].guard.margin: must be >= 0, got -1"),
    (lambda d: d["robot"].__setitem__("guard", {"brake": 2}), "robot.guard.brake: unknown field (allowed: decel, enabled, lag_s, margin, slide_after_s, slide_free)"),
    (lambda d: d["robot"].__setitem__("stuck", {"detour": {"lookahed": 2}}), "robot.stuck.detour.lookahed: unknown field"),
    (lambda d: d["robots"][0].__setitem__("stuck", {"window": 0}), "robots[0].stuck.window: must be > 0, got 0"),
    (lambda d: d["robot"].__setitem__("guard", {"slide_after_s": -1}), "robot.guard.slide_after_s: must be >= 0, got -1"),
    (lambda d: d["robots"][1].__setitem__("guard", {"slide_free": 0}), "robots[1].guard.slide_free: must be > 0, got 0"),
    (lambda d: d["robot"].__setitem__("stuck", {"detour": {"straight_time": 0}}),
     "robot.stuck.detour.straight_time: must be > 0, got 0"),
]


@pytest.mark.parametrize("mutate,message", BAD, ids=[m for _, m in BAD])
def test_bad_field_named(mutate, message):
    with pytest.raises(ScenarioError) as e:
        parse_scenario(_bad(mutate), "s.yaml")
    assert str(e.value).startswith(f"s.yaml: {message}"), str(e.value)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("mutate,message", BAD[:3], ids=[m for _, m in BAD[:3]])
def test_bad_scenario_file_exits_2_with_one_line(tmp_path, mutate, message):
    path = write_scenario(tmp_path / "bad.yaml", _bad(mutate))
    proc = run_cli(["stack-fleet", "run", str(path), "--out", str(tmp_path / "out")], timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"bad.yaml: {message}" in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_unparseable_yaml_and_missing_file(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("dt: [0.1\nrobots: {")
    proc = run_cli(["stack-fleet", "run", str(p)], timeout=60)
    assert proc.returncode == 2 and "broken.yaml: line" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_cli(["stack-fleet", "run", str(tmp_path / "nope.yaml")], timeout=60)
    assert proc.returncode == 2 and "nope.yaml: cannot read" in proc.stderr


@pytest.mark.parametrize("flags,message", [
    (["--loss", "2"], "--loss: expected a probability in [0, 1], got '2'"),
    (["--kill", "two@3"], "--kill: expected ID@SECONDS"),
    (["--kill", "9@3"], "--kill 9@3: no robot with id 9"),
    (["--policy", "nonsense"], "--policy: invalid choice"),
    (["--listen", "tcp/10.0.0.1:7447"], "not a loopback address"),
    (["--duration", "0"], "--duration: expected a number > 0"),
    (["--lockstep-timeout", "0"], "--lockstep-timeout: must be > 0, got 0"),
])
def test_bad_flags_exit_2(diamond, flags, message):
    proc = run_cli(["stack-fleet", "run", str(diamond), *flags], timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_gui_without_display_is_bad_input(diamond):
    proc = run_cli(["stack-fleet", "run", str(diamond), "--gui"], timeout=60, unset=("DISPLAY", "WAYLAND_DISPLAY"))
    assert proc.returncode == 2 and "--gui: no display" in proc.stderr, proc.stderr


def test_overrides_apply_and_revalidate():
    sc = parse_scenario(scenario_dict(), "s.yaml")
    o = with_overrides(sc, loss=0.3, latency_ms=50, seed=9, duration=5)
    assert (o.comm.loss, o.comm.latency_ms, o.seed, o.duration) == (0.3, 50, 9, 5)
    with pytest.raises(ScenarioError, match="comm.loss: must be <= 1"):
        with_overrides(sc, loss=3.0)
    assert sc.comm.loss == 0.0  # the original is untouched
    raw = copy.deepcopy(sc.raw)
    assert raw == scenario_dict()


def test_agent_without_a_router_says_so_in_one_line():
    from stack.comm.session import free_tcp_endpoint

    proc = run_cli(["stack-agent", "--id", "1", "--scenario", str(SCENARIOS / "four-robot-diamond.yaml"),
                    "--connect", free_tcp_endpoint()], timeout=60)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot reach a Zenoh router at tcp/127.0.0.1:" in lines[0], proc.stderr


@pytest.mark.parametrize("argv,message", [
    (["--role", "leader"], "--role: robot 1 is follower"),
    (["--steps", "0"], "--steps: must be >= 1"),
    (["--connect", "tcp/192.168.1.5:7447"], "not a loopback address"),
    (["--id", "9"], "robots: no robot with id 9"),
])
def test_agent_bad_flags_exit_2(argv, message):
    args = ["stack-agent", "--id", "1", "--scenario", str(SCENARIOS / "four-robot-diamond.yaml")]
    if argv[0] == "--id":
        args[2] = argv[1]
        argv = []
    proc = run_cli(args + argv, timeout=60)
    assert proc.returncode == 2 and message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_fleet_listen_port_in_use_is_bad_input(diamond):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        proc = run_cli(["stack-fleet", "run", str(diamond), "--listen", f"tcp/127.0.0.1:{port}"], timeout=60)
    assert proc.returncode == 2 and "address in use" in proc.stderr, proc.stderr


def test_formation_schedule_switches_slots_in_time():
    d = scenario_dict()
    d["formation"]["schedule"] = [{"at": 5.0, "slots": {1: {"L": 1.0, "psi_deg": 180}}},
                                  {"at": 9.5, "slots": {2: {"L": 2.0, "psi_deg": 90}, 1: {"L": 3.0, "psi_deg": 0}}}]
    f = parse_scenario(d).formation
    assert f.slots_at(0.0) == f.slots and f.slots_at(4.99) == f.slots
    at5 = f.slots_at(5.0)
    assert at5[1].L == 1.0 and at5[2] == f.slots[2] and at5[3] == f.slots[3]  # a change keeps the followers it leaves out
    assert f.final_slots[1].L == 3.0 and f.final_slots[2].L == 2.0 and f.final_slots[3] == f.slots[3]


def test_plugin_blocks_merge_per_robot_over_the_defaults():
    from stack.policies.drl.config import DrlConfig

    d = scenario_dict()
    d["robot"]["qlearn"] = {"cell": 0.25, "n_headings": 8}
    d["robot"]["can"] = {"channel": "vcan0"}
    d["robots"][1] |= {"policy": "qlearn", "qlearn": {"n_headings": 12}, "can": {"node_left": 2}}
    d["robots"][3]["policy"] = "fuzzy-lstm"
    sc = parse_scenario(d)
    q0, q1 = sc.robot(0).config_for("qlearn"), sc.robot(1).config_for("qlearn")
    assert (q0.cell, q0.n_headings) == (0.25, 8) and (q1.cell, q1.n_headings) == (0.25, 12)
    assert sc.robot(2).config_for("drl") == DrlConfig() and "drl" not in sc.robot(2).settings  # defaults when absent
    assert set(sc.robot(1).settings) == {"pid", "qlearn"} and set(sc.robot(3).settings) == {"pid", "qlearn", "fuzzy"}
    assert "QlearnPolicyConfig(cell=0.25" in repr(sc.robot(1))  # the resolved config, as the agent logs its robot
    assert sc.robot(0).driver_params["can"] == {"channel": "vcan0"}
    assert sc.robot(1).driver_params["can"] == {"channel": "vcan0", "node_left": 2}
    with pytest.raises(KeyError, match="no policy takes robot.lidar settings"):
        sc.robot(0).config_for("lidar")


def test_device_settings_resolve_per_driver_and_bad_ones_are_one_line():
    """``robot.device``: ``ideal`` for every simulated device, then a block per driver, checked by that device's config."""
    import yaml

    d = yaml.safe_load((SCENARIOS / "mixed-drivers.yaml").read_text())
    d["robot"]["device"] = {"ideal": False, "jackal": {"lidar_rate_hz": 15}}
    d["robots"][1]["device"] = {"can": {"power_up_pos_rev": [0.25, 0.5]}}
    sc = parse_scenario(d, "m.yaml")
    by_driver = {r.driver: r.device for r in sc.robots}
    assert by_driver["jackal"] == {"ideal": False, "lidar_rate_hz": 15}
    assert by_driver["can"] == {"ideal": False, "power_up_pos_rev": [0.25, 0.5]}
    assert by_driver["mavlink"] == {"ideal": False} and by_driver["sim"] == {}
    for bad, words in (({"jackal": {"lidar_rate": 15}}, "robot.device.jackal.lidar_rate: unknown field"),
                       ({"ideal": 3}, "robot.device.ideal: expected true or false"),
                       ({"jackal": {"lidar_rate_hz": -1}}, "device.jackal: lidar_rate_hz must be > 0"),
                       ({"bogus": {}}, "robot.device.bogus: unknown field")):
        d["robot"]["device"] = bad
        with pytest.raises(ScenarioError, match=re.escape(words)):
            parse_scenario(d, "m.yaml")


def test_site_datum():
    d = scenario_dict(site={"datum": [47.3977, 8.5456, 488.0]})
    assert parse_scenario(d, "s.yaml").site.datum == (47.3977, 8.5456, 488.0)
    assert parse_scenario(scenario_dict(), "s.yaml").site.datum is None
    for bad, words in (([47.0, 8.0], "site.datum: expected 3 numbers, got 2"), ([95.0, 0.0, 0.0], "site.datum[0]: must be <= 89"),
                       ([0.0, 200.0, 0.0], "site.datum[1]: must be <= 180")):
        with pytest.raises(ScenarioError, match=re.escape(words)):
            parse_scenario(scenario_dict(site={"datum": bad}), "s.yaml")
