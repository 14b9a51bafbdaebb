"""MessagePack message types of the wire format.

Every payload is a MessagePack map with named fields, readable by any MessagePack decoder
in any language. Decoding validates types and finiteness; unknown extra fields are
ignored (the contract lets senders add fields), missing required ones are errors.
"""

from __future__ import annotations

import math

import msgspec


class MessageError(ValueError):
    """A payload that does not decode or validate: to be dropped and counted, never raised to a loop."""


def _finite(obj: msgspec.Struct) -> None:
    for name in obj.__struct_fields__:
        v = getattr(obj, name)
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{name} is not finite")


class _Msg(msgspec.Struct, kw_only=True):
    def __post_init__(self) -> None:
        _finite(self)


class State(_Msg):
    """``stack/<fleet>/<id>/state``: an agent's own estimate, sent once per control step."""

    id: int
    role: str
    seq: int
    stamp: float  # sim time in lock-step, wall clock (UNIX s) in real time
    x: float
    y: float
    yaw: float
    v: float
    w: float
    step: int = -1
    cov_trace: float | None = None
    situation: str | None = None
    wall: float | None = None  # sender's wall clock at sending (UNIX s), for latency measurement
    d_goal: float | None = None  # arrival-time peers: the sender's distance to its own goal [m] (Chang 2020's D_goal)

    def __post_init__(self) -> None:
        _finite(self)
        if self.d_goal is not None and self.d_goal < 0:
            raise ValueError("d_goal must be >= 0")


class CmdVel(_Msg):
    """``.../cmd_vel``: body-frame command to a simulated or bridged base. step -1: outside the step loop (a stop)."""

    id: int
    step: int
    stamp: float
    v: float
    w: float


class Answer(_Msg):
    """``.../answer``: lock-step only: the agent has commanded step ``step`` through a driver whose wire
    carries no step (a hosted device: CAN, MAVLink, a bridged ROS 2 base); its command is on that wire."""

    id: int
    step: int
    stamp: float
    wire: int | None = None  # messages the driver has put on the device's wire so far (None: not counted)
    sync: bool = False  # the agent's first step (a fresh start or a restart: a new driver, its count from 0)


class Odom(_Msg):
    """``.../odom``: wheel odometry, body-frame speeds measured by the encoders, and the pose the
    base integrated from them (as a real base's odometry topic carries; None if it has none)."""

    id: int
    step: int
    stamp: float
    v: float
    w: float
    x: float | None = None
    y: float | None = None
    yaw: float | None = None


class Imu(_Msg):
    """``.../imu``: gyro yaw rate."""

    id: int
    step: int
    stamp: float
    wz: float


class Fix(_Msg):
    """``.../fix``: an absolute position fix (GNSS, mocap, or the simulated stand-in), world frame."""

    id: int
    step: int
    stamp: float
    x: float
    y: float
    std: float

    def __post_init__(self) -> None:
        _finite(self)
        if not self.std > 0:
            raise ValueError("std must be > 0")


class Scan(_Msg):
    """``.../scan``: 2D lidar, ``ranges[i]`` at angle_min + i * angle_increment (robot frame), metres."""

    id: int
    step: int
    stamp: float
    angle_min: float
    angle_increment: float
    range_max: float
    ranges: list[float]

    def __post_init__(self) -> None:
        _finite(self)
        if not self.ranges or len(self.ranges) > 100_000:
            raise ValueError("ranges length out of bounds")
        for r in self.ranges:
            if not (0.0 <= r <= self.range_max):
                raise ValueError("range outside [0, range_max]")


class Clock(_Msg):
    """``stack/<fleet>/world/clock``: the world's step k and sim time; ``answered`` is who commanded step k-1."""

    step: int
    t: float
    dt: float
    answered: list[int] = []
    lockstep: bool = True
    dead: list[int] = []  # robots whose agents are gone (killed or left) as of this step
    device_odom: dict[int, int] = {}  # robot id -> odometry samples its hosted device has sent since lock-step began


class FaultRequest(_Msg):
    """``stack/<fleet>/world/fault``: the world asks whoever started the agents to inject a fault at
    step ``step`` (kill: SIGKILL, freeze: SIGSTOP, restart: start the agent again). Driven by the
    world's own clock so lock-step runs with faults stay repeatable."""

    step: int
    t: float
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
    t: float
    ids: list[int]
    x: list[float]
    y: list[float]
    yaw: list[float]


class WorldStatus(_Msg):
    """``stack/<fleet>/world/status``: ready, running, done (with why)."""

    state: str
    t: float = 0.0
    why: str = ""


class Diag(_Msg):
    """``.../diag``: an agent's counters, loop timing histogram and situation counts."""

    id: int
    stamp: float
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
    state_latency_hist: dict[int, int] = {}
    situations: dict[str, int] = {}
    fixes_used: int = 0
    fixes_rejected: int = 0
    inputs_rejected: int = 0  # NaN/inf/negative inputs the estimator dropped
    sensor_stale: int = 0  # real time: times the robot was stopped because its sensors went stale
    fault: str = ""
    noticed: dict[int, float] = {}  # robot id -> sim time this agent dropped it (gone)
    led_since: float | None = None  # sim time this agent took over as leader (failover)
    rejected_states: int = 0  # neighbours' states that claimed an impossible jump
    neighbour_waits_timed_out: int = 0  # lock-step steps that went on without an awaited neighbour state
    device_odom_late: int = 0  # lock-step steps that went on without all of the device's odometry samples of the step
    device_odom_strays: int = 0  # lock-step: device odometry samples that belonged to no step (dropped)
    odom_stale: int = 0  # control steps commanded zero because the odometry was stale
    lidar_stale: int = 0  # control steps commanded zero because the lidar was stale (policies that need it)
    scans_from_driver: int = 0  # real time: scans the robot's own driver read (a Jackal's LaserScan)
    shield_masked: int | None = None  # --policy drl: steps at which the action shield overruled the network
    links: dict[int, dict[str, int]] | None = None  # sender id -> {delivered, dropped_range, dropped_loss}, cumulative
    # (RadioModel.links()): the comm graph a recorder draws; None from senders that do not count per link
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
