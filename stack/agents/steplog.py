"""The step log: every input of a control step and what the step returned, one JSON message a step.

``StepPipeline.step(StepInputs) -> StepOutput`` is a function of its inputs and of the pipeline's settings,
so a robot's run is reproduced, to the bit, by building the same pipeline and feeding it the same inputs in
order (``stack-replay``). This module is that record's one definition: the schema (:class:`StepRecord`,
version :data:`VERSION`), how the agent writes it (:class:`StepLogger`, on the control loop: one encode)
and how a reader turns it back into :class:`~.step.StepInputs` (:func:`inputs_of`).

Channel ``/robot_<id>/step_io`` (JSON, schema ``stack.viz.messages.JSON_SCHEMAS['step_io']``), in ``stack-agent --record FILE`` and
in a fleet run's ``run.mcap`` (the agents publish it on ``stack/<fleet>/<id>/step_io`` when the
fleet records). The first record of an agent's life (``n`` = 0; again after a restart) carries the
:class:`Setup`: the resolved scenario, the policy, the seed and the step's own settings.

Exact floats: JSON numbers are written as the shortest decimal that reads back to the same float
(msgspec), so every finite value survives. A device may hand over a non-finite rate (the estimator
rejects and counts it); such values in the odometry and fixes are written as the strings ``"nan"``,
``"inf"``, ``"-inf"``. Scans and neighbours' states are finite by their wire checks.

A scan that is the same as the previous step's (a lidar slower than the control period repeats its
newest) is written once: later records say ``scan_same: true``.
"""

from __future__ import annotations

import math
from dataclasses import asdict

import msgspec

from ..comm.messages import Scan, State
from .step import OdomSample, StepInputs, StepOutput

VERSION = 1
"""The step log's schema version; a reader refuses a newer one (one line), never guesses."""
WHAT = "step_io"
"""The topic's last part: ``/robot_<id>/step_io`` in MCAP, ``stack/<fleet>/<id>/step_io`` on Zenoh."""

F = float | str  # a float; "nan", "inf", "-inf" where it is not finite


class Setup(msgspec.Struct, kw_only=True, omit_defaults=True):
    """How the agent built its pipeline (``StepPipeline(scenario, robot, policy=, seed=, config=)``)."""

    version: int
    robot: int
    scenario: str
    """The resolved scenario as YAML (every override applied: what the agent ran)."""
    source: str
    """Where the scenario came from (relative paths in it are relative to this)."""
    policy: str
    seed: int | None
    step_config: dict
    """``StepConfig``'s fields (``guard`` as a mapping)."""
    lockstep: bool
    driver: str
    stack: str
    """The stack's version that wrote the log."""


class Odom(msgspec.Struct, kw_only=True, omit_defaults=True):
    """One :class:`~.step.OdomSample`."""

    v: F
    w: F
    t: F
    wz_imu: F | None = None
    pose: list[F] | None = None
    fix: list[F] | None = None


class FixXY(msgspec.Struct):
    """One absolute position fix (site frame) of ``StepInputs.fixes`` (an object: viewers read no nested arrays)."""

    x: F
    y: F
    std: F


class StateRefs(msgspec.Struct):
    """The neighbours' states a step took, by name (a fleet's recording has each state once, on
    ``/robot_<id>/state``): sender ids, their ``seq`` and ``stamp`` (together unique, a restart's too)."""

    id: list[int]
    seq: list[int]
    stamp: list[float]


class Out(msgspec.Struct, kw_only=True, omit_defaults=True):
    """What the step returned (:class:`~.step.StepOutput`), the role it left, and the guard's counters."""

    v: float
    w: float
    pose: list[float]  # x, y, yaw, v, w
    situation: str
    cov_trace: float
    d_goal: float | None
    stale: str | None
    target: list[float] | None
    role: str
    guard_caps: int
    guard_slides: int
    heard: list[int] = []
    """The neighbour table after the step (ids): the states the radio model delivered, as far as they are current."""


class StepRecord(msgspec.Struct, kw_only=True, omit_defaults=True):
    """One control step: everything :class:`~.step.StepInputs` carried, and :class:`Out`."""

    version: int
    id: int
    n: int
    """Records since this agent started: 0, 1, 2, ... (a gap: records lost on the way)."""
    step: int
    t: float
    t_run: float
    now: float
    odometry: list[Odom] = []
    scan: Scan | None = None
    scan_same: bool = False
    """The step's scan is the previous record's (written once)."""
    scan_t: float | None = None
    fixes: list[FixXY] = []
    states: list[State] = []
    state_refs: StateRefs | None = None
    """Instead of ``states``, in a fleet's recording: which states, by name (every agent hears every state: copied
    into each robot's record they would grow with the square of the fleet)."""
    dead: list[int] = []
    held: str | None = None
    goal: list[float] | None = None
    plans: list[int] | None = None
    """The plans (``stack.planning.runner`` tickets) this step adopted; None: a log from before the runners (its
    plans were adopted as they were asked for)."""
    out: Out
    cmd: list[float]
    """What the driver was commanded (after its limits)."""
    setup: Setup | None = None


class Head(msgspec.Struct):
    """The fields a recorder needs to place a record (decoding the rest is the replay's work)."""

    id: int
    n: int
    step: int
    t: float
    now: float


class LogError(ValueError):
    """A record that does not decode, or one from another schema version (one line)."""


def _f(x: float) -> F:
    return x if math.isfinite(x) else repr(x)  # 'nan', 'inf', '-inf'


def _unf(x: F) -> float:
    return float(x)


def _fs(xs) -> list[F] | None:
    return None if xs is None else [_f(float(x)) for x in xs]


def _odom(s: OdomSample) -> Odom:
    return Odom(v=_f(s.v), w=_f(s.w), t=_f(s.t), wz_imu=None if s.wz_imu is None else _f(s.wz_imu),
                pose=_fs(s.pose), fix=_fs(s.fix))


def out_of(out: StepOutput, pipeline) -> Out:
    """The record of a step's output, with what the pipeline holds after it (role, guard counters, neighbours)."""
    p, pl = out.pose, pipeline
    return Out(v=out.v, w=out.w, pose=[p.x, p.y, p.yaw, p.v, p.w], situation=out.situation, cov_trace=out.cov_trace,
               d_goal=out.d_goal, stale=out.stale, target=None if out.target is None else [float(c) for c in out.target],
               role=pl.role, guard_caps=pl.guard.capped, guard_slides=pl.guard.slides, heard=sorted(pl.neighbours))


def setup_of(pipeline, lockstep: bool, driver: str) -> Setup:
    from .. import __version__

    cfg = asdict(pipeline.cfg)
    return Setup(version=VERSION, robot=pipeline.id, scenario=pipeline.sc.to_yaml(), source=pipeline.sc.source,
                 policy=pipeline.policy_name, seed=pipeline.seed, step_config=cfg, lockstep=lockstep, driver=driver,
                 stack=__version__)


class StepLogger:
    """The agent's side: :meth:`record` turns one step into the bytes of one message (control loop; one encode).
    ``refs``: the neighbours' states by name (:class:`StateRefs`: for a fleet's recording, which has them)."""

    def __init__(self, pipeline, lockstep: bool, driver: str, refs: bool = False):
        self.pl, self.refs = pipeline, refs
        self.setup: Setup | None = setup_of(pipeline, lockstep, driver)
        self.n = 0
        self._scan: Scan | None = None
        self._enc = msgspec.json.Encoder()

    def record(self, inp: StepInputs, out: StepOutput, cmd: tuple[float, float]) -> bytes:
        same = inp.scan is not None and inp.scan is self._scan
        pl = self.pl
        rec = StepRecord(
            version=VERSION, id=pl.id, n=self.n, step=inp.step, t=inp.t, t_run=inp.t_run, now=inp.now,
            odometry=[_odom(s) for s in inp.odometry], scan=None if same else inp.scan, scan_same=same,
            scan_t=inp.scan_t, fixes=[FixXY(*map(_f, fx)) for fx in inp.fixes],
            states=[] if self.refs else list(inp.states), state_refs=_refs(inp.states) if self.refs else None,
            dead=sorted(inp.dead), held=inp.held, goal=None if inp.goal is None else list(inp.goal),
            plans=list(pl.planner.adopted_now), out=out_of(out, pl), cmd=[float(cmd[0]), float(cmd[1])], setup=self.setup)
        self.n += 1
        self.setup = None
        if inp.scan is not None:
            self._scan = inp.scan
        return self._enc.encode(rec)


def _refs(states) -> StateRefs:
    return StateRefs([m.id for m in states], [m.seq for m in states], [m.stamp for m in states])


# --- the reader's side ---------------------------------------------------------------------------------------
_HEAD = msgspec.json.Decoder(Head)
_RECORD = msgspec.json.Decoder(StepRecord)
_VERSION = msgspec.json.Decoder(dict)


def head(payload: bytes) -> Head:
    try:
        return _HEAD.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise LogError(f"not a step record ({e})") from None


def decode(payload: bytes) -> StepRecord:
    """One record; LogError naming what is wrong (a newer schema version says so first)."""
    try:
        rec = _RECORD.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        try:
            version = _VERSION.decode(payload).get("version")
        except msgspec.DecodeError:
            version = None
        if isinstance(version, int) and version != VERSION:
            raise _version_error(version) from None
        raise LogError(f"a step record that does not decode ({e})") from None
    if rec.version != VERSION:  # it decoded (unknown fields are skipped), but what they mean may have changed
        raise _version_error(rec.version)
    return rec


def _version_error(version: int) -> LogError:
    newer = " (a newer stack wrote it: replay it with that one)" if version > VERSION else ""
    return LogError(f"schema version {version}, this stack reads version {VERSION}{newer}")


def inputs_of(rec: StepRecord, previous_scan: Scan | None) -> StepInputs:
    """The :class:`~.step.StepInputs` a record carries (``previous_scan``: the last record's, for ``scan_same``; a
    record with ``state_refs`` has had them resolved into ``states`` by its reader)."""
    odometry = tuple(OdomSample(v=_unf(o.v), w=_unf(o.w), t=_unf(o.t),
                                wz_imu=None if o.wz_imu is None else _unf(o.wz_imu),
                                pose=None if o.pose is None else tuple(map(_unf, o.pose)),
                                fix=None if o.fix is None else tuple(map(_unf, o.fix))) for o in rec.odometry)
    scan = previous_scan if rec.scan_same else rec.scan
    return StepInputs(step=rec.step, t=rec.t, t_run=rec.t_run, now=rec.now, odometry=odometry, scan=scan,
                      scan_t=rec.scan_t, fixes=tuple((_unf(fx.x), _unf(fx.y), _unf(fx.std)) for fx in rec.fixes),
                      states=tuple(rec.states), dead=frozenset(rec.dead), held=rec.held,
                      goal=None if rec.goal is None else (rec.goal[0], rec.goal[1]),
                      plans=None if rec.plans is None else tuple(rec.plans))


__all__ = ["VERSION", "WHAT", "Head", "LogError", "Out", "Setup", "StateRefs", "StepLogger", "StepRecord", "decode", "head",
           "inputs_of", "out_of"]
