"""Lock-step state relay (``stack.comm.lockstep.StateRelay``): the world hears every agent's state once and hands
them on in the next clock, so no lock-step agent subscribes per sender."""

from __future__ import annotations

import json
import threading
import time

import msgspec
import pytest

from conftest import run_fleet, scenario_dict, write_scenario
from stack.comm import encode
from stack.comm.lockstep import StateRelay
from stack.comm.messages import State


def _state(rid: int, step: int) -> bytes:
    return encode(State(id=rid, role="follower", seq=step, stamp=0.1 * step, step=step, x=float(rid), y=0.0, yaw=0.0,
                        v=0.0, w=0.0))


def _relay(wait_s: float = 5.0, **kw) -> tuple[StateRelay, threading.Event]:
    return StateRelay(threading.Condition(), wait_s, **kw), threading.Event()


def test_take_waits_for_the_state_of_every_robot_that_answered():
    """Robot 2's state of step 4 comes 0.3 s after take() began (its command was heard first): take() returns only
    then, with everything heard in arrival order, robot 9 (which did not answer) not waited for."""
    relay, stop = _relay()
    relay.on_state("stack/f/1/state", _state(1, 4))
    later = threading.Timer(0.3, relay.on_state, ("stack/f/2/state", _state(2, 4)))
    t0 = time.monotonic()
    later.start()
    got = relay.take(4, [1, 2], stop)
    waited = time.monotonic() - t0
    assert [r.key for r in got] == ["stack/f/1/state", "stack/f/2/state"]
    assert [r.payload for r in got] == [_state(1, 4), _state(2, 4)]
    assert waited >= 0.25 and relay.late == 0
    assert relay.take(5, [], stop) == []  # each payload goes out once


def test_a_state_heard_before_the_clock_asked_counts_and_a_newer_one_too():
    relay, stop = _relay()
    relay.on_state("stack/f/1/state", _state(1, 7))  # a newer step than asked for: robot 1 is not missing
    relay.on_state("stack/f/2/state", _state(2, 6))
    t0 = time.monotonic()
    got = relay.take(6, [1, 2], stop)
    assert len(got) == 2 and time.monotonic() - t0 < 1.0 and relay.late == 0


def test_a_missing_state_makes_the_clock_late_not_stuck():
    relay, stop = _relay(wait_s=0.2)
    relay.on_state("stack/f/1/state", _state(1, 2))  # of an older step: robot 1's state of 3 never comes
    got = relay.take(3, [1], stop)
    assert len(got) == 1 and relay.late == 1


def test_unreadable_payloads_are_relayed_for_the_agents_to_count_but_never_awaited():
    """Garbage and a map without an id go on in the clock (the agents decode and count them by their key, as
    before); they do not stand in for robot 1's awaited state."""
    relay, stop = _relay(wait_s=0.3)
    junk = [b"\xc1", b"\x81\xa1x\x01", msgspec.msgpack.encode({"id": "one", "step": 3})]
    for p in junk:
        relay.on_state("stack/f/1/state", p)
    got = relay.take(3, [1], stop)
    assert [r.payload for r in got] == junk and relay.late == 1


def test_a_flood_beyond_the_byte_limit_is_dropped_and_counted():
    relay, stop = _relay(limit_bytes=1000)
    p = _state(1, 0)
    n = 3 * 1000 // len(p)
    for _ in range(n):
        relay.on_state("stack/f/1/state", p)
    got = relay.take(0, [], stop)
    assert len(got) == 1000 // len(p) and relay.dropped == n - len(got)
    relay.on_state("stack/f/1/state", p)  # the next clock has room again
    assert len(relay.take(1, [], stop)) == 1


def test_stop_ends_the_wait():
    relay, stop = _relay(wait_s=30.0)
    threading.Timer(0.2, stop.set).start()
    t0 = time.monotonic()
    assert relay.take(1, [5], stop) == []
    assert time.monotonic() - t0 < 5.0


@pytest.mark.fleet
def test_every_state_reaches_every_neighbour_through_the_clock(tmp_path):
    """Six lock-step agents, no loss, all in range: every state an agent sent is received by each of the five
    others (each robot's state of the last step excepted: the run may end before a clock carries it), none late, none dropped."""
    poses = [[0.0, 0.0, 0.0], [-2.0, 2.0, 0.0], [-2.0, -2.0, 0.0], [-4.0, 2.0, 0.0], [-4.0, -2.0, 0.0], [-6.0, 0.0, 0.0]]
    robots = [{"id": i, "role": "leader" if i == 0 else "follower", "pose": p} for i, p in enumerate(poses)]
    slots = {1: {"L": 2.8, "psi_deg": 135}, 2: {"L": 2.8, "psi_deg": -135}, 3: {"L": 4.5, "psi_deg": 153},
             4: {"L": 4.5, "psi_deg": -153}, 5: {"L": 6.0, "psi_deg": 180}}
    sc = scenario_dict(robots=robots, formation={"leader": 0, "goal": [12.0, 0.0], "slots": slots})
    sc["duration"] = 3.0
    sc["robot"]["comm_range"] = 50.0
    out = tmp_path / "out"
    proc, rep = run_fleet(write_scenario(tmp_path / "six.yaml", sc), out, "--no-plots", "--no-record")
    assert rep is not None, proc.stderr
    n, comm = 6, rep["comm"]
    assert comm["malformed"] == 0 and comm["dropped_loss"] == 0 and comm["dropped_range"] == 0, comm
    assert (n - 1) * (comm["broadcasts"] - n) <= comm["received"] <= (n - 1) * comm["broadcasts"], comm
    assert comm["broadcasts"] >= n * 25  # three seconds of steps
    world = json.loads((out / "world.json").read_text())
    assert world["states_late"] == 0 and world["states_dropped"] == 0
