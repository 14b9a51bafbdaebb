"""Malformed payloads on every key an agent or the world subscribes to: counted, never a crash.

Real Zenoh sessions (a router session and clients in this process), a real agent and a
real world server running lock-step in threads while hypothesis throws payloads at them.
"""

from __future__ import annotations

import math
import threading
import time

import msgpack
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import scenario_dict
from stack.agents.agent import Agent, AgentConfig
from stack.comm import Keys, MessageError, decode
from stack.comm.messages import Clock, CmdVel, Imu, Odom, Scan, State
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session
from stack.scenario import parse_scenario
from stack.sim_bridge.server import WorldConfig, WorldServer

FLEET = "fuzz"
VALID = {
    State: {"id": 7, "role": "follower", "seq": 1, "stamp": 0.0, "x": 0.0, "y": 0.0, "yaw": 0.0, "v": 0.0, "w": 0.0},
    Scan: {"id": 0, "step": 1, "stamp": 0.0, "angle_min": -1.5, "angle_increment": 0.1, "range_max": 5.0, "ranges": [1.0, 2.0]},
    Odom: {"id": 0, "step": 1, "stamp": 0.0, "v": 0.0, "w": 0.0},
    Imu: {"id": 0, "step": 1, "stamp": 0.0, "wz": 0.0},
    Clock: {"step": 1, "t": 0.1, "dt": 0.1},
    CmdVel: {"id": 0, "step": 1, "stamp": 0.0, "v": 0.0, "w": 0.0},
}
KEYS = {State: "7/state", Scan: "0/scan", Odom: "0/odom", Imu: "0/imu", Clock: "world/clock", CmdVel: "0/cmd_vel"}

junk = st.recursive(st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats(allow_nan=True) | st.text(max_size=8),
                    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4), max_leaves=8)


@st.composite
def near_valid(draw, kind):
    d = dict(VALID[kind])
    field = draw(st.sampled_from(sorted(d)))
    if draw(st.booleans()):
        del d[field]
    else:
        d[field] = draw(st.sampled_from(["text", None, [1, "x"], {"k": 1}, math.nan, math.inf, -1e400, 2**63, -2**63]) | junk)
    return msgpack.packb(d)


def payloads(kind):
    return st.binary(max_size=400) | junk.map(lambda j: msgpack.packb(j)) | near_valid(kind)


def _invalid_for(kind, payload: bytes) -> bool:
    try:
        m = decode(payload, kind)
    except MessageError:
        return True
    return kind is not Clock and getattr(m, "id", None) != (7 if kind is State else 0)


@pytest.fixture(scope="module")
def running_fleet():
    ep = free_tcp_endpoint()
    sc = parse_scenario(scenario_dict(robots=[{"id": 0, "role": "leader", "pose": [0, 0, 0]}],
                                      formation={"leader": 0, "goal": [500.0, 0.0], "slots": {}}, duration=100000.0), "fuzz.yaml")
    with open_session(SessionConfig(mode="router", listen=[ep])), \
            open_session(SessionConfig(connect=[ep])) as s_agent, \
            open_session(SessionConfig(connect=[ep])) as s_world, \
            open_session(SessionConfig(connect=[ep])) as s_fuzz:
        acfg = AgentConfig(robot_id=0, scenario=sc, connect=ep, fleet=FLEET, lockstep=True)
        agent = Agent(acfg, s_agent)
        wcfg = WorldConfig(scenario=sc, connect=ep, fleet=FLEET, lockstep_timeout_s=5.0, stop_early=False)
        world = WorldServer(wcfg, s_world)
        errors = []

        def guard(fn):
            def run():
                try:
                    fn()
                except BaseException as e:  # noqa: BLE001 - the test reports it
                    errors.append(e)
            return run

        ta = threading.Thread(target=guard(agent.run), daemon=True)
        tw = threading.Thread(target=guard(world.run), daemon=True)
        ta.start()
        tw.start()
        deadline = time.monotonic() + 20
        while agent.step < 5 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert agent.step >= 5, errors
        yield agent, world, s_fuzz, errors
        acfg.stop.set()
        wcfg.stop.set()
        ta.join(10)
        tw.join(15)


def _wait_counts(agent, world, want_agent: int, want_world: int, timeout: float = 10.0) -> None:
    """Until the agent's and the world's drop counters reach the wanted totals (or the timeout)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if sum(agent.malformed.values()) >= want_agent and world.malformed >= want_world:
            return
        time.sleep(0.002)


def test_malformed_payloads_are_counted(running_fleet):
    """Every invalid payload hypothesis draws, on every key, is counted as exactly one drop, example by
    example; afterwards both still step and nothing raised."""
    agent, world, s, errors = running_fleet
    step0 = agent.step
    sent = {"agent": 0, "world": 0}

    @settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck))
    @given(data=st.data())
    def feed(data):
        # draw everything before sending: hypothesis may abandon an example inside a draw
        drawn = [(kind, key, data.draw(payloads(kind), label=kind.__name__)) for kind, key in KEYS.items()]
        before_a, before_w = sum(agent.malformed.values()), world.malformed
        n_agent = n_world = 0
        for kind, key, payload in drawn:
            if not _invalid_for(kind, payload):
                continue
            s.put(f"stack/{FLEET}/{key}", payload, congestion_control=zenoh.CongestionControl.BLOCK)
            if kind is CmdVel:
                n_world += 1
            else:
                n_agent += 1
        _wait_counts(agent, world, before_a + n_agent, before_w + n_world)
        assert sum(agent.malformed.values()) - before_a == n_agent, agent.malformed
        assert world.malformed - before_w == n_world
        sent["agent"] += n_agent
        sent["world"] += n_world

    feed()
    assert sent["agent"] > 100 and sent["world"] > 20, sent  # the strategies do reach every key
    assert set(agent.malformed) <= {"state", "scan", "odom", "imu", "clock"}
    time.sleep(0.5)
    assert agent.step > step0  # still stepping
    assert not errors


def test_valid_but_wrong_scan_and_odd_keys_are_counted(running_fleet):
    """A scan that decodes but does not fit the robot's lidar, and a key with a non-ASCII digit: counted, no crash."""
    agent, world, s, errors = running_fleet
    before = sum(agent.malformed.values())
    scan = dict(VALID[Scan]) | {"step": 10**6, "ranges": [1.0, 2.0]}
    s.put(f"stack/{FLEET}/0/scan", msgpack.packb(scan), congestion_control=zenoh.CongestionControl.BLOCK)
    s.put(f"stack/{FLEET}/\u00b2/state", msgpack.packb(VALID[State]), congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + 5
    while sum(agent.malformed.values()) < before + 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert sum(agent.malformed.values()) == before + 2
    step0 = agent.step
    time.sleep(0.5)
    assert agent.step > step0 and not errors


def _bulk_payloads(n: int, rng) -> list[bytes]:
    """Random bytes, truncated valid messages, wrongly typed maps and a few oversized payloads."""
    valid = [msgpack.packb(v) for v in VALID.values()]
    wrong = [msgpack.packb(dict(v) | {k: "x"}) for v in VALID.values() for k in v]
    out = []
    for i in range(n):
        r = i % 4
        if r == 0:
            out.append(rng.randbytes(rng.randrange(0, 64)))
        elif r == 1:
            p = valid[i % len(valid)]
            out.append(p[: rng.randrange(0, len(p))])
        elif r == 2:
            out.append(wrong[i % len(wrong)])
        else:
            out.append(b"\xdd\xff\xff\xff\xff" if i % 10_000 != 3 else b"\xc4\x00" + rng.randbytes(200_000))
    return out


def test_hundred_thousand_hostile_messages_counted_nobody_crashed(running_fleet):
    """100,000 malformed, truncated, oversized and wrongly typed payloads over every key the agent and
    the world listen on (scan, odom, imu, fix, a neighbour's state, the clock; cmd_vel, fault_ack):
    every one is counted as a drop, and both keep stepping."""
    import random

    agent, world, s, errors = running_fleet
    rng = random.Random(5)
    agent_keys = ["0/scan", "0/odom", "0/imu", "0/fix", "7/state", "world/clock"]
    world_keys = ["0/cmd_vel", "world/fault_ack"]
    before_a, before_w = sum(agent.malformed.values()), world.malformed
    pubs = {k: s.declare_publisher(f"stack/{FLEET}/{k}", congestion_control=zenoh.CongestionControl.BLOCK)
            for k in agent_keys + world_keys}
    n_agent = n_world = 0
    keys = agent_keys + world_keys
    for i, payload in enumerate(_bulk_payloads(100_000, rng)):
        key = keys[i % len(keys)]
        pubs[key].put(payload)
        if key in agent_keys:
            n_agent += 1
        else:
            n_world += 1
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if sum(agent.malformed.values()) - before_a >= n_agent and world.malformed - before_w >= n_world:
            break
        time.sleep(0.1)
    assert sum(agent.malformed.values()) - before_a == n_agent, (agent.malformed, n_agent)
    assert world.malformed - before_w == n_world
    step0 = agent.step
    time.sleep(0.5)
    assert agent.step > step0 and not errors
    for p in pubs.values():
        p.undeclare()


def test_a_state_claiming_a_teleport_is_rejected(running_fleet, monkeypatch):
    """Of three states from robot 7, the third claims 7 m in 0.1 s: it is judged against the second (kept)
    and rejected. The judgement is recorded where the agent makes it: the kept state goes stale
    (3 s of simulated time) within a few tens of ms of lock-step, too soon to read it afterwards."""
    agent, world, s, errors = running_fleet
    pipeline = agent.pipeline  # the control step (stack/agents/step.py) judges neighbours' states
    before = pipeline.counters.rejected_states
    judged = []
    plausible = pipeline._plausible

    def spy(old, m):
        ok = plausible(old, m)
        judged.append((old.x, m.x, ok))
        return ok

    monkeypatch.setattr(pipeline, "_plausible", spy)
    pose, t0 = agent.estimator.pose, agent.sim_now
    for i, dx in enumerate((1.0, 1.05, 8.0)):  # then 7 m in 0.1 s from a robot that drives 1 m/s at most
        st_ = dict(VALID[State]) | {"seq": 100 + i, "step": 0, "stamp": t0 + 0.1 * i, "x": pose.x + dx, "y": pose.y}
        s.put(f"stack/{FLEET}/7/state", msgpack.packb(st_), congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + 5
    while pipeline.counters.rejected_states == before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert pipeline.counters.rejected_states == before + 1
    x1, x2, x3 = pose.x + 1.0, pose.x + 1.05, pose.x + 8.0
    assert judged[-2:] == [(x1, x2, True), (x2, x3, False)], judged  # the plausible one was kept, the jump dropped
    assert not errors
