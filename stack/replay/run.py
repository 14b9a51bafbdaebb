"""Replaying a robot's step log through its step pipeline, unchanged or changed, and comparing to the bit.

Open-loop: the replayed pipeline gets the recorded inputs whatever it commands (the world does not answer a
replayed command). Unchanged, each step's output must equal the recorded one bit for bit (every float compared
by its bits: ``-0.0`` differs from ``0.0``, a NaN matches only the same NaN); changed (:class:`Changes`), the
first step that differs is where the change first mattered, and after it the inputs are those of the recorded
robot, not of one that drove the changed commands.
"""

from __future__ import annotations

import copy
import logging
import struct
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import yaml

from ..agents import steplog
from ..agents.guard import GuardConfig
from ..agents.step import StepConfig, StepPipeline
from ..agents.steplog import LogError, Out, Setup
from ..planning.runner import ScriptedRunner, ThreadRunner
from ..robotfile import layer, read_robot_file
from ..scenario import Scenario, ScenarioError, parse_scenario
from .log import RobotLog

OUT_FIELDS = ("v", "w", "pose", "situation", "cov_trace", "d_goal", "stale", "target", "role", "guard_caps",
              "guard_slides", "heard")


@dataclass
class Changes:
    """What the replay changes against the recorded settings (none: a check that the log reproduces)."""

    robot_file: str | None = None
    """A robot settings file layered over the robot's entry (``stack-agent --robot``'s form)."""
    sets: list[str] = field(default_factory=list)
    """``KEY=VALUE``: ``robot.K.K2=V`` sets K.K2 in this robot's entry; any other key is the scenario's (``comm.loss``)."""
    policy: str | None = None
    """Another policy."""

    @property
    def any(self) -> bool:
        return bool(self.robot_file or self.sets or self.policy)


@dataclass
class Row:
    step: int
    t: float
    recorded: Out
    replayed: Out
    ns: int = 0  # the record's log time in the file


@dataclass
class Result:
    robot: int
    rows: list[Row]
    first: Row | None = None
    """The first step whose output differs, or None: every step reproduced."""
    differs: tuple[str, ...] = ()
    """Which of its fields differ."""
    segments: int = 0

    @property
    def reproduced(self) -> bool:
        return self.first is None


def _bits(x) -> object:
    """A value as compared: floats by their bits, lists item by item."""
    if isinstance(x, float):
        return struct.pack("<d", x)
    if isinstance(x, list):
        return tuple(_bits(v) for v in x)
    return x


def differing(a: Out, b: Out) -> tuple[str, ...]:
    return tuple(f for f in OUT_FIELDS if _bits(getattr(a, f)) != _bits(getattr(b, f)))


def _set(raw: dict, robot: int, assignment: str) -> None:
    key, sep, text = assignment.partition("=")
    if not sep or not key or any(not part for part in key.split(".")):
        raise ScenarioError(f"--set {assignment!r}: expected KEY=VALUE, e.g. robot.pid.k_w=2.5")
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        raise ScenarioError(f"--set {key}: {text!r} is not a value") from None
    parts = key.split(".")
    if parts[0] == "robot":
        entries = [r for r in raw.get("robots", []) if isinstance(r, dict) and r.get("id") == robot]
        node, parts = entries[0], parts[1:]
    else:
        node = raw
    for p in parts[:-1]:
        nxt = node.get(p)
        if nxt is None:
            nxt = node[p] = {}
        if not isinstance(nxt, dict):
            raise ScenarioError(f"--set {key}: {p} is not a mapping in the recorded settings")
        node = nxt
    node[parts[-1]] = value


def scenario_of(setup: Setup, changes: Changes) -> Scenario:
    """The scenario the agent ran with (its resolved YAML), with ``changes`` applied; ScenarioError (one line)."""
    raw = yaml.safe_load(setup.scenario)
    if changes.robot_file:
        raw = layer(raw, setup.robot, read_robot_file(changes.robot_file), changes.robot_file)
    for s in changes.sets:
        _set(raw, setup.robot, s)
    try:
        return parse_scenario(raw, setup.source)
    except ScenarioError as e:
        if changes.any:
            raise ScenarioError(f"the recorded settings with the changes: {e}") from None
        raise


def pipeline_of(setup: Setup, changes: Changes) -> StepPipeline:
    """The agent's pipeline, built as the agent built it (``Agent.__init__``), with ``changes``."""
    if setup.version != steplog.VERSION:
        raise LogError(f"setup of schema version {setup.version}, this stack reads version {steplog.VERSION}")
    sc = scenario_of(setup, changes)
    d = copy.deepcopy(setup.step_config)
    names = {f.name for f in fields(StepConfig)}
    if set(d) - names:
        raise LogError(f"setup: step settings this stack does not know: {sorted(set(d) - names)}")
    policy = changes.policy or setup.policy
    if changes.robot_file or any(s.startswith("robot.policy=") for s in changes.sets):
        policy = changes.policy or sc.robot(setup.robot).policy
    try:
        d["guard"] = GuardConfig(**d.get("guard", {}))
        pl = StepPipeline(sc, setup.robot, policy=policy, seed=setup.seed, config=StepConfig(**d))
    except (TypeError, ValueError) as e:  # settings this stack's pipeline refuses
        raise LogError(f"setup: the recorded step settings do not build a pipeline here ({e})") from None
    # plans: adopted at the steps the log says; with changes, the plans asked for differ: the lock-step rule
    pl.use_planner(ThreadRunner(lockstep_steps=1) if changes.any else ScriptedRunner())
    return pl


def replay(log: RobotLog, changes: Changes | None = None, progress=None) -> Result:
    """Every step of every segment through a fresh pipeline; the first difference is kept, and the rest replayed."""
    changes = changes or Changes()
    res = Result(log.robot, [])
    quiet = logging.getLogger("stack.agent")
    level, quiet.level = quiet.level, logging.ERROR  # the pipeline's own log lines (role changes) are the agent's
    try:
        for seg in log.segments:
            pl = pipeline_of(seg.setup, changes)
            res.segments += 1
            scan = None
            for rec, ns in zip(seg.records, seg.stamps):
                inp = steplog.inputs_of(rec, scan)
                if changes.any:
                    inp = replace(inp, plans=None)  # the lock-step rule, not the recorded steps
                scan = inp.scan
                try:
                    out = pl.step(inp)
                except Exception as e:  # noqa: BLE001 - a record the step cannot take (edited, or another version's)
                    raise LogError(f"robot {log.robot}, step {rec.step}: the step pipeline raised "
                                   f"{type(e).__name__}: {e}") from None
                row = Row(rec.step, rec.t_run, rec.out, steplog.out_of(out, pl), ns)
                res.rows.append(row)
                if res.first is None and (d := differing(row.recorded, row.replayed)):
                    res.first, res.differs = row, d
                if progress is not None:
                    progress()
            pl.planner.close()
    finally:
        quiet.level = level
    return res


def largest(res: Result, n: int = 10) -> list[Row]:
    """The ``n`` steps with the largest command differences (|dv| + |dw|), largest first."""
    rows = [r for r in res.rows if differing(r.recorded, r.replayed)]
    rows.sort(key=lambda r: -(abs(r.replayed.v - r.recorded.v) + abs(r.replayed.w - r.recorded.w)))
    return rows[:n]


def describe_first(res: Result) -> str:
    r = res.first
    a, b = r.recorded, r.replayed
    parts = []
    for f in res.differs:
        x, y = getattr(a, f), getattr(b, f)
        if isinstance(x, float) and isinstance(y, float):
            parts.append(f"{f} {x:.6g} -> {y:.6g} (diff {y - x:+.3g})")
        elif f == "pose":
            parts.append("estimate (" + ", ".join(f"{u:.4f}" for u in x[:3]) + ") -> (" +
                         ", ".join(f"{u:.4f}" for u in y[:3]) + ")")
        else:
            parts.append(f"{f} {x!r} -> {y!r}")
    return f"first divergence: step {r.step} (t={r.t:.2f} s), robot {res.robot}: " + "; ".join(parts)


def check_out_dir(out: str | Path) -> Path:
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise ScenarioError(f"--out {out}: exists and is not a folder")
    return p
