"""The wire format: MessagePack maps with named fields that any decoder reads (here: plain msgpack)."""

from __future__ import annotations

import math

import msgpack
import pytest

from stack.comm import MessageError, decode, encode
from stack.comm.keys import Keys
from stack.comm.messages import CmdVel, Scan, State


def test_state_is_a_plain_msgpack_map_with_the_contract_fields():
    b = encode(State(id=2, role="follower", seq=5, stamp=1.5, x=1.0, y=-2.0, yaw=0.3, v=0.5, w=-0.1, step=15))
    m = msgpack.unpackb(b)
    assert isinstance(m, dict)
    for k in ("id", "role", "seq", "stamp", "x", "y", "yaw", "v", "w"):
        assert k in m
    assert (m["id"], m["role"], m["x"]) == (2, "follower", 1.0)


def test_state_d_goal_is_optional_and_checked():
    """Arrival-time peers add d_goal (their distance to their own goal); older senders leave it out."""
    s = decode(encode(State(id=1, role="peer", seq=1, stamp=0.0, x=0, y=0, yaw=0, v=0, w=0, d_goal=12.5)), State)
    assert s.d_goal == 12.5
    assert decode(encode(State(id=1, role="peer", seq=1, stamp=0.0, x=0, y=0, yaw=0, v=0, w=0)), State).d_goal is None
    with pytest.raises(MessageError):
        decode(msgpack.packb({"id": 1, "role": "peer", "seq": 1, "stamp": 0.0, "x": 0, "y": 0, "yaw": 0.0, "v": 0.0,
                              "w": 0.0, "d_goal": math.inf}), State)
    with pytest.raises(MessageError):
        decode(msgpack.packb({"id": 1, "role": "peer", "seq": 1, "stamp": 0.0, "x": 0, "y": 0, "yaw": 0.0, "v": 0.0,
                              "w": 0.0, "d_goal": -1.0}), State)


def test_foreign_encoder_with_extra_fields_decodes():
    b = msgpack.packb({"id": 3, "role": "leader", "seq": 1, "stamp": 0.0, "x": 1, "y": 2, "yaw": 0.0, "v": 0.0,
                       "w": 0.0, "battery": 0.8})
    s = decode(b, State)
    assert (s.id, s.x, s.step) == (3, 1.0, -1)


@pytest.mark.parametrize("bad", [
    {"id": 1, "step": 0, "stamp": 0.0, "v": math.nan, "w": 0.0},
    {"id": 1, "step": 0, "stamp": 0.0, "v": "fast", "w": 0.0},
    {"id": 1, "step": 0, "stamp": 0.0, "w": 0.0},
])
def test_invalid_cmd_vel_raises_message_error(bad):
    with pytest.raises(MessageError):
        decode(msgpack.packb(bad), CmdVel)


def test_scan_ranges_checked():
    ok = {"id": 0, "step": 0, "stamp": 0.0, "angle_min": -1.0, "angle_increment": 0.1, "range_max": 5.0}
    assert decode(msgpack.packb(ok | {"ranges": [0.5, 5.0]}), Scan).ranges == [0.5, 5.0]
    for bad in ([], [6.0], [-0.1], [math.nan]):
        with pytest.raises(MessageError):
            decode(msgpack.packb(ok | {"ranges": bad}), Scan)


def test_keys():
    k = Keys("f")
    assert k.robot(2, "state") == "stack/f/2/state"
    assert k.world("clock") == "stack/f/world/clock"
    assert k.alive(4) == "stack/f/alive/4"
    assert Keys.id_of("stack/f/2/state") == 2 and Keys.id_of("stack/f/alive/4") == 4
    assert Keys.id_of("stack/f/world/clock") is None and Keys.id_of("junk") is None
