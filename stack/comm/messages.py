"""MessagePack message types of the wire format.

Every payload is a MessagePack map with named fields, readable by any MessagePack decoder
in any language. Decoding validates types and finiteness; unknown extra fields are
ignored (the contract lets senders add fields), missing required ones are errors.

The checks are msgspec constraints (``Finite``: NaN and +-inf fail its bounds), run by msgspec's C decoder:
a per-field Python check cost a State's decode six times its parse (docs/profile.md), and at 32 robots each
agent decodes 31 states a step. What needs two fields (a scan's ranges within its ``range_max``) stays in
``__post_init__``. Constructing a message checks only that; a receiver drops what does not decode.
"""

from __future__ import annotations

import sys
from typing import Annotated

import msgspec

_MAX = sys.float_info.max
Finite = Annotated[float, msgspec.Meta(ge=-_MAX, le=_MAX)]
"""A float that decodes only when finite."""
NonNegative = Annotated[float, msgspec.Meta(ge=0.0, le=_MAX)]
Positive = Annotated[float, msgspec.Meta(gt=0.0, le=_MAX)]


class MessageError(ValueError):
    """A payload that does not decode or validate: to be dropped and counted, never raised to a loop."""


class _Msg(msgspec.Struct, kw_only=True):
    """A message; its float fields are ``Finite`` (or narrower)."""


class State(_Msg):
    """``stack/<fleet>/<id>/state``: an agent's own estimate, sent once per control step."""

    id: int
    role: str
    seq: int
    stamp: Finite  # sim time in lock-step, wall clock (UNIX s) in real time
    x: Finite
    y: Finite
    yaw: Finite
    v: Finite
    w: Finite
    step: int = -1
    cov_trace: Finite | None = None
    situation: str | None = None
    wall: Finite | None = None  # sender's wall clock at sending (UNIX s), for latency measurement
    d_goal: NonNegative | None = None  # arrival-time peers: the sender's distance to its own goal [m] (Chang 2020's D_goal)


class CmdVel(_Msg):
    """``.../cmd_vel``: body-frame command to a simulated or bridged base. step -1: outside the step loop (a stop)."""

    id: int
    step: int
    stamp: Finite
    v: Finite
    w: Finite


class Answer(_Msg):
    """``.../answer``: lock-step only: the agent has commanded step ``step`` through a driver whose wire
    carries no step (a hosted device: CAN, MAVLink, a bridged ROS 2 base); its command is on that wire."""

    id: int
    step: int
    stamp: Finite
    wire: int | None = None  # messages the driver has put on the device's wire so far (None: not counted)
    sync: bool = False  # the agent's first step (a fresh start or a restart: a new driver, its count from 0)


class Odom(_Msg):
    """``.../odom``: wheel odometry, body-frame speeds measured by the encoders, and the pose the
    base integrated from them (as a real base's odometry topic carries; None if it has none)."""

    id: int
    step: int
    stamp: Finite
    v: Finite
    w: Finite
    x: Finite | None = None
    y: Finite | None = None
    yaw: Finite | None = None


class Imu(_Msg):
    """``.../imu``: gyro yaw rate."""

    id: int
    step: int
    stamp: Finite
    wz: Finite


class Fix(_Msg):
    """``.../fix``: an absolute position fix (GNSS, mocap, or the simulated stand-in), world frame."""

    id: int
    step: int
    stamp: Finite
    x: Finite
    y: Finite
    std: Positive


class Scan(_Msg):
    """``.../scan``: 2D lidar, ``ranges[i]`` at angle_min + i * angle_increment (robot frame), metres."""

    id: int
    step: int
    stamp: Finite
    angle_min: Finite
    angle_increment: Finite
    range_max: Finite
    ranges: Annotated[list[NonNegative], msgspec.Meta(min_length=1, max_length=100_000)]

    def __post_init__(self) -> None:
        if not self.ranges or max(self.ranges) > self.range_max:  # each one finite and >= 0: the decoder checked
            raise ValueError("ranges empty or beyond range_max")


class Relayed(_Msg):
    """A message the world heard on ``key`` and passes on undecoded (``Clock.states``): the receiver decodes,
    validates and counts it as if it had come on ``key`` itself."""

    key: str
    payload: bytes


class Clock(_Msg):
    """``stack/<fleet>/world/clock``: the world's step k and sim time; ``answered`` is who commanded step k-1.

    In lock-step ``states`` carries every ``.../state`` payload the world heard since the previous clock (the
    states of step k-1 of every robot that commanded k-1, and any late one), so a lock-step agent needs no
    subscription per sender (``stack.comm.lockstep.StateRelay``); empty in real time."""

    step: int
    t: Finite
    dt: Finite
    answered: list[int] = []
    lockstep: bool = True
    dead: list[int] = []  # robots whose agents are gone (killed or left) as of this step
    device_odom: dict[int, int] = {}  # robot id -> odometry samples its hosted device has sent since lock-step began
    device_scans: dict[int, int] = {}  # robot id -> whole scans its hosted lidar has sent since lock-step began
    states: list[Relayed] = []  # lock-step: the agents' states heard since the previous clock, undecoded


class FaultRequest(_Msg):
    """``stack/<fleet>/world/fault``: the world asks whoever started the agents to inject a fault at
    step ``step`` (kill: SIGKILL, freeze: SIGSTOP, restart: start the agent again). Driven by the
    world's own clock so lock-step runs with faults stay repeatable."""

    step: int
    t: Finite
    kind: str
    ids: list[int]


class FaultAck(_Msg):
    """``stack/<fleet>/world/fault_ack``: the request of ``step`` was carried out (``done``: the ids)."""

    step: int
    kind: str
    done: list[int] = []


class Truth(_Msg):
    """``stack/<fleet>/world/truth``: ground truth, for the orchestrator and tools only, never agents."""

    step: int
    t: Finite
    ids: list[int]
    x: list[float]
    y: list[float]
    yaw: list[float]
    real: list[int] = []  # robots outside the world (embodiment real): their x, y, yaw are their pose source's
    stale: list[int] = []  # real robots whose pose source went stale: the body stands at the last pose, grown


class WorldStatus(_Msg):
    """``stack/<fleet>/world/status``: ready, running, done (with why)."""

    state: str
    t: Finite = 0.0
    why: str = ""


class Diag(_Msg):
    """``.../diag``: an agent's counters, loop timing histogram and situation counts."""

    id: int
    stamp: Finite
    step: int
    state: str  # running | stopped | fault
    sent: int = 0
    received: int = 0
    delivered: int = 0
    dropped_loss: int = 0
    dropped_range: int = 0
    malformed: int = 0
    malformed_by_key: dict[str, int] = {}
    loop_hist: dict[int, int] = {}
    compute_hist: dict[int, int] = {}  # the agent's own work a step: inputs taken -> command sent [ms buckets]
    state_latency_hist: dict[int, int] = {}
    situations: dict[str, int] = {}
    fixes_used: int = 0
    fixes_rejected: int = 0
    inputs_rejected: int = 0  # NaN/inf/negative inputs the estimator dropped
    sensor_stale: int = 0  # real time: times the robot was stopped because its sensors went stale
    fault: str = ""
    noticed: dict[int, float] = {}  # robot id -> sim time this agent dropped it (gone)
    led_since: Finite | None = None  # sim time this agent took over as leader (failover)
    rejected_states: int = 0  # neighbours' states that claimed an impossible jump
    neighbour_waits_timed_out: int = 0  # lock-step steps that went on without an awaited neighbour state
    device_odom_late: int = 0  # lock-step steps that went on without all of the device's odometry samples of the step
    device_odom_strays: int = 0  # lock-step: device odometry samples that belonged to no step (dropped)
    led: list[list[Finite]] = []  # [start, end] run times this agent led (the leader's role, not held)
    link_outages: list[list[Finite | None]] = []  # real time: [start, end] run times its session had no router
    held_steps: int = 0  # control steps held at zero: no router (its own loss) or a leader without a quorum
    tokens_kept: int = 0  # peers' liveliness tokens that went away with our own link (the peers were kept)
    virtual: dict[str, int] | None = None  # a real robot with lidar.virtual: received, merged_scans, merged_returns, lost_steps
    odom_stale: int = 0  # control steps commanded zero because the odometry was stale
    lidar_stale: int = 0  # control steps commanded zero because the lidar was stale (policies that need it)
    scans_from_driver: int = 0  # real time: scans the robot's own driver read (a Jackal's LaserScan)
    shield_masked: int | None = None  # --policy drl: steps at which the action shield overruled the network
    guard_caps: int = 0  # steps at which the collision guard lowered the policy's forward speed
    guard_slides: int = 0  # steps at which a robot the guard held still took its way out (GuardConfig.slide_after_s)
    guard_brakes: int = 0  # steps commanded zero: the base still rolled with something inside the margin ahead
    links: dict[int, dict[str, int]] | None = None  # sender id -> {delivered, dropped_range, dropped_loss}, cumulative
    # (RadioModel.links()): the comm graph a recorder draws; None from senders that do not count per link
    planner: dict | None = None  # plans beside the step (PlanRunner.stats): asked, adopted, compute ms, ages [s]
    stuck: dict | None = None  # stuck episodes, what resolved them, the leader hold's give-ups (stack.agents.livelock)


_ENCODER = msgspec.msgpack.Encoder()
_DECODERS: dict[type, msgspec.msgpack.Decoder] = {}


def encode(msg: msgspec.Struct) -> bytes:
    return _ENCODER.encode(msg)


def decode(payload: bytes, kind: type[msgspec.Struct]):
    """Decode and validate; raise :class:`MessageError` with a short reason."""
    dec = _DECODERS.get(kind)
    if dec is None:
        dec = _DECODERS[kind] = msgspec.msgpack.Decoder(kind)
    try:
        return dec.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise MessageError(f"{kind.__name__}: {e}") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as e:  # defensive: any decoder fault is a drop
        raise MessageError(f"{kind.__name__}: {e}") from None


def receive(sample, kind: type[msgspec.Struct], on_malformed=None):
    """Decode a zenoh sample's payload as ``kind``; on failure call ``on_malformed(key)`` and return None."""
    try:
        return decode(sample.payload.to_bytes(), kind)
    except MessageError:
        if on_malformed is not None:
            on_malformed(str(sample.key_expr))
        return None
