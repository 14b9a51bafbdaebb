"""Issue 20: a robot's own view, ``stack-agent --record FILE`` and ``stack-agent --viz [EP]``.

The fleet tests start a router, the agents (as the robots would be: ``--external-agents``), one of them
recording and one serving live, and ``stack-fleet run --connect ... --external-agents`` for the world."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, run_cli, run_fleet, scenario_dict, wait_for, wait_port, write_scenario
from stack.comm.session import free_tcp_endpoint
from stack.viz import messages as vm
from test_install import _run_without_extras
from test_record import _start_router, _stop, _ws_client, read_mcap

PY = sys.executable
ENV = dict(os.environ, PYTHONUNBUFFERED="1")
SCHEMAS = {"/tf_estimate": "foxglove.FrameTransforms", "/scene/obstacles": "foxglove.SceneUpdate", "/events": "foxglove.Log"}
ROBOT_SCHEMAS = {"estimate": "foxglove.PoseInFrame", "scan": "foxglove.LaserScan", "scene": "foxglove.SceneUpdate",
                 "links": "foxglove.SceneUpdate", "cmd_vel": "stack.CmdVel", "state": "stack.State", "diag": "stack.Diag",
                 "covariance": "stack.Covariance", "decision": "stack.Decision", "heard": "stack.Heard",
                 "step_io": "stack.StepRecord"}
PER_STEP = ("estimate", "scan", "scene", "links", "cmd_vel", "state", "covariance", "decision", "heard", "step_io")


def _want(rid: int) -> dict[str, str]:
    return SCHEMAS | {vm.robot_topic(rid, k): s for k, s in ROBOT_SCHEMAS.items()}


def _live_client(port: int, seen: dict, advertised: dict, stop: threading.Event) -> None:
    """test_record's protocol client, until the agent's server closes (the agent ends with the world)."""
    import websockets

    try:
        _ws_client(port, seen, advertised, stop)
    except websockets.exceptions.ConnectionClosed:
        pass


def _agent(path: Path, robot: dict, ep: str, fleet: str, logs: Path, *extra: str) -> subprocess.Popen:
    argv = [PY, "-m", "stack.agents", "--id", str(robot["id"]), "--role", robot["role"], "--scenario", str(path),
            "--connect", ep, "--fleet", fleet, "--log-level", "INFO", *extra]
    return subprocess.Popen(argv, stdout=open(logs / f"agent-{robot['id']}.log", "wb"), stderr=subprocess.STDOUT,
                            cwd=ROOT, env=ENV)


# --- bad input ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ep, why", [("tcp/10.1.2.3:8765", "not a loopback"), ("udp/127.0.0.1:8765", "WebSocket over tcp")])
def test_a_bad_agent_viz_endpoint_is_one_line_and_exit_2(diamond, ep, why):
    p = run_cli(["stack-agent", "--id", "1", "--scenario", str(diamond), "--connect", "tcp/127.0.0.1:9", "--viz", ep],
                timeout=60)
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert p.stderr.startswith("stack-agent: --viz:") and why in p.stderr


def test_an_agent_file_it_cannot_write_is_one_line_and_exit_2(tmp_path, diamond):
    (tmp_path / "f").write_text("a file, not a folder")
    ep, router = _start_router(tmp_path)
    try:
        p = run_cli(["stack-agent", "--id", "1", "--scenario", str(diamond), "--connect", ep, "--record",
                     str(tmp_path / "f" / "view.mcap")], timeout=60)
    finally:
        _stop(router)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and p.stderr.startswith("stack-agent: recorder:"), p.stderr


def test_an_agent_without_the_sdk_is_told_which_extra_in_one_line():
    p = _run_without_extras("""
        import sys
        from stack.agents.cli import cli
        sys.argv = ["stack-agent", "--id", "1", "--scenario", "scenarios/four-robot-obstacles.yaml", "--record", "x.mcap",
                    "--connect", "tcp/127.0.0.1:9"]
        sys.exit(cli())
    """)
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert p.stderr.strip().splitlines() == ["stack-agent: --record needs the Python package 'foxglove', not installed here "
                                             "(install the 'viz' extra: pip install 'formation-stack[viz]')"]


# --- a lock-step fleet: one robot records, one serves live ----------------------------------------------------
def _check_view(path: Path, rid: int, steps: int, dt: float) -> dict:
    summary, msgs, meta, att = read_mcap(path)
    schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert schemas == _want(rid)
    t = lambda k: vm.robot_topic(rid, k)  # noqa: E731
    for k in PER_STEP:  # one per control step: the agent answered every one of the world's
        assert len(msgs[t(k)]) == steps, k
    assert len(msgs["/tf_estimate"]) == steps
    assert [ns for ns, _ in msgs[t("state")]] == [round(k * dt * 1e9) for k in range(steps)]  # sim time
    assert [m["step"] for _, m in msgs[t("decision")]] == list(range(steps))
    assert len(msgs[t("diag")]) == len(range(0, steps, 10)) + 1 and msgs[t("diag")][-1][1]["state"] == "stopped"
    assert len(msgs["/scene/obstacles"]) == math.ceil(steps * dt - 1e-9)
    m = meta["stack.agent"]
    assert (m["robot"], m["time"], m["steps"], m["dropped"], m["malformed"]) == (str(rid), "sim", str(steps), "0", "0")
    assert b"test-diamond" in att["scenario.yaml"]
    return msgs


@pytest.mark.fleet
def test_agents_record_and_serve_their_own_view_in_a_lockstep_fleet(tmp_path):
    sc, port = scenario_dict(duration=4.0), int(free_tcp_endpoint().rsplit(":", 1)[1])
    path = write_scenario(tmp_path / "d.yaml", sc)
    seen, advertised, stop = {}, {}, threading.Event()  # what the live client counts, what it was offered
    ep, router = _start_router(tmp_path)
    extra = {1: ["--record", str(tmp_path / "view-1.mcap")],
             2: ["--viz", f"tcp/127.0.0.1:{port}", "--record", str(tmp_path / "view-2.mcap")]}
    out = tmp_path / "out"
    fleet = subprocess.Popen([PY, "-m", "stack.fleet", "run", str(path), "--out", str(out), "--no-progress", "--no-plots",
                              "--connect", ep, "--fleet", "av1", "--external-agents", "--wait-agents", "180"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT, env=ENV)
    # the world first (it waits for every agent), then robot 2 and its live client, then the others: the world's
    # first step comes once all are up, and no agent waits long for it (a lock-step agent gives up after 30 s)
    agents = {2: _agent(path, sc["robots"][2], ep, "av1", tmp_path, "--lockstep", *extra[2])}
    try:
        wait_port(f"tcp/127.0.0.1:{port}", timeout=120)  # an agent starts in seconds; a loaded machine takes longer
        client = threading.Thread(target=_live_client, args=(port, seen, advertised, stop), daemon=True)
        client.start()
        assert wait_for(lambda: len(advertised) == len(_want(2)), timeout=20), advertised  # subscribed before step 0
        agents |= {r["id"]: _agent(path, r, ep, "av1", tmp_path, "--lockstep", *extra.get(r["id"], []))
                   for r in sc["robots"] if r["id"] != 2}
        log = fleet.communicate(timeout=300)[0]
        assert (out / "report.json").exists(), log
        codes = [agents[i].wait(60) for i in range(4)]  # lock-step agents end when the world is done
        assert codes == [0] * 4, (codes, [(tmp_path / f"agent-{i}.log").read_text()[-400:] for i in range(4)])
        stop.set()
        client.join(10)
    finally:
        stop.set()
        for a in [fleet, *agents.values()]:
            _stop(a)
        _stop(router)
    steps = json.loads((out / "world.json").read_text())["steps"]
    msgs = _check_view(tmp_path / "view-1.mcap", 1, steps, sc["dt"])
    _check_view(tmp_path / "view-2.mcap", 2, steps, sc["dt"])
    # its estimate is the one it sent (the fleet's recording has its states), its scan the world's, in its estimate's frame
    _, recorded, _, _ = read_mcap(out / "run.mcap")
    mine = [(ns, m.pose.position.x, m.pose.position.y) for ns, m in msgs["/robot_1/estimate"]]
    sent = [(ns, m.pose.position.x, m.pose.position.y) for ns, m in recorded["/robot_1/estimate"]]
    assert mine == sent
    assert [list(m.ranges) for _, m in msgs["/robot_1/scan"]] == [list(m.ranges) for _, m in recorded["/robot_1/scan"]]
    assert {m.frame_id for _, m in msgs["/robot_1/scan"]} == {"robot_1/estimate"}
    cov = [m for _, m in msgs["/robot_1/covariance"]]
    assert all(len(c["cov"]) == 9 and np.isclose(c["cov"][0] + c["cov"][4] + c["cov"][8], c["cov_trace"]) for c in cov)
    # a follower steers to its slot behind the leader it hears, and hears the other three
    decisions = [m for _, m in msgs["/robot_1/decision"]]
    assert {d["role"] for d in decisions} == {"follower"} and decisions[-1]["situation"].startswith("follower")
    assert decisions[-1]["goal"] == [8.0, 0.0] and len(decisions[-1]["target"]) == 2
    heard = [m for _, m in msgs["/robot_1/heard"]]
    assert {n["id"] for n in heard[-1]["neighbours"]} == {0, 2, 3}
    assert sum(h["delivered"] for h in heard) > 0 and all(h["dropped_range"] == h["dropped_loss"] == 0 for h in heard)
    events = [m.message for _, m in msgs["/events"]]
    assert events[0].startswith("robot 1: agent up") and "0 dropped" in events[-1]
    # the live client: every channel advertised and received while the fleet ran
    assert advertised == _want(2)
    assert set(seen) == set(_want(2)), sorted(set(_want(2)) - set(seen))
    assert seen["/robot_2/state"] == steps
    _clean_in_lichtblick(tmp_path, "view-1.mcap", _want(1), msgs["/robot_1/state"][-1][0])
    # issue 40: the robot's own recording replays to the bit (stack-replay FILE: one robot, no --robot-id)
    p = run_cli(["stack-replay", str(tmp_path / "view-1.mcap")])
    assert p.returncode == 0 and f"robot 1: {steps} steps replayed: every output reproduced to the bit" in p.stdout, \
        p.stdout + p.stderr


def _clean_in_lichtblick(folder: Path, name: str, topics, at_ns: int) -> None:
    """Issue 38: a robot's own recording opens in the real viewer (tests/lichtblick.py) with no problem reported
    (every JSON schema readable: the covariance, the decision, the neighbour table) and every topic listed."""
    from lichtblick import Viewer

    with Viewer(folder) as v:
        v.open_recording(name, at_ns=at_ns)
        v.page.wait_for_timeout(2000)
        problems, listed = v.problems(), set(v.topics())
    assert not problems, "the viewer reports:\n" + "\n".join(problems)
    assert set(topics) <= listed, sorted(set(topics) - listed)


@pytest.mark.fleet
def test_a_realtime_agent_records_on_wall_time_and_stops_after_its_steps(tmp_path):
    sc = scenario_dict(duration=4.0)
    path = write_scenario(tmp_path / "d.yaml", sc)
    ep, router = _start_router(tmp_path)
    agents = [_agent(path, r, ep, "av2", tmp_path, *(["--steps", "20", "--record", str(tmp_path / "v.mcap")]
                                                     if r["id"] == 3 else [])) for r in sc["robots"]]
    try:
        t0 = time.time_ns()
        proc, rep = run_fleet(path, tmp_path / "out", "--connect", ep, "--fleet", "av2", "--external-agents", "--realtime",
                              "--no-plots", "--no-record")
        t1 = time.time_ns()
        assert rep is not None, proc.stderr
        assert agents[3].wait(30) == 0
    finally:
        for a in agents:
            _stop(a)
        _stop(router)
    _, msgs, meta, _ = read_mcap(tmp_path / "v.mcap")
    assert meta["stack.agent"]["time"] == "wall" and meta["stack.agent"]["steps"] == "20"
    for k in PER_STEP:
        assert len(msgs[vm.robot_topic(3, k)]) == 20, k
    times = [ns for ns, _ in msgs["/robot_3/state"]]
    assert t0 < times[0] < times[-1] < t1
    assert 0.05 < np.median(np.diff(times)) / 1e9 < 0.2  # its own period, dt = 0.1 s
    p = run_cli(["stack-replay", str(tmp_path / "v.mcap")])  # a real-time agent's own log replays to the bit
    assert p.returncode == 0 and "robot 3: 20 steps replayed: every output reproduced to the bit" in p.stdout, \
        p.stdout + p.stderr
