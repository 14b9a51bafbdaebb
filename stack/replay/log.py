"""Reading a robot's step log (``/robot_<id>/step_io``) back out of an MCAP file, whole or torn.

The file is read as a stream (``mcap.stream_reader.StreamReader``), not through its summary: a log cut short
(the robot lost power, the file was copied half-way) has no summary, and a torn last record is where the
reading stops, counted, keeping every whole step before it. A record's ``n`` counts the agent's steps from 0,
so a record lost on the way (a full queue, a drop on the wire) shows as a gap: the replay stops before it
(what follows depends on the lost step). Each agent life (a restart: ``n`` = 0 again, with its
:class:`~stack.agents.steplog.Setup`) is a segment of its own.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from ..agents import steplog
from ..agents.steplog import LogError, Setup, StepRecord
from ..comm.messages import State

TOPIC = re.compile(r"^/robot_(\d+)/" + steplog.WHAT + "$")
STATE_TOPIC = re.compile(r"^/robot_(\d+)/state$")
STATE_FIELDS = set(State.__struct_fields__)


@dataclass
class Segment:
    """One agent life: its setup and its records, in order."""

    setup: Setup
    records: list[StepRecord] = field(default_factory=list)
    stamps: list[int] = field(default_factory=list)
    """Each record's log time in the file [ns]."""


@dataclass
class RobotLog:
    robot: int
    path: Path
    segments: list[Segment]
    stopped: str | None = None
    """Why reading stopped before the file's end (a torn tail, a gap), or None."""
    skipped: int = 0
    """Records not replayed: after a gap, or before the first setup (the recording began mid-life)."""

    @property
    def steps(self) -> int:
        return sum(len(s.records) for s in self.segments)


@dataclass
class _Raw:
    steps: dict[int, list[tuple[bytes, int]]]  # robot -> (payload, log time), in file order
    states: list[bytes]  # every /robot_<id>/state payload (a fleet's records name the states they took)
    stopped: str | None  # why the reading stopped early (None: the whole file)


def _raw(path: Path) -> _Raw:
    """Every step_io payload per robot, in file order, and every state; and why the reading stopped early."""
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    out: dict[int, list[tuple[bytes, int]]] = {}
    states: list[bytes] = []
    topics: dict[int, int] = {}  # channel id -> robot (step_io)
    state_topics: set[int] = set()
    stopped = None
    with path.open("rb") as f:
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Channel) and (m := TOPIC.match(rec.topic)):
                    topics[rec.id] = int(m.group(1))
                elif isinstance(rec, Channel) and STATE_TOPIC.match(rec.topic) and rec.message_encoding == "json":
                    state_topics.add(rec.id)
                elif isinstance(rec, Message) and rec.channel_id in topics:
                    out.setdefault(topics[rec.channel_id], []).append((rec.data, rec.log_time))
                elif isinstance(rec, Message) and rec.channel_id in state_topics:
                    states.append(rec.data)
        except Exception as e:  # noqa: BLE001 - a torn or corrupt tail (mcap raises several kinds): stop, counted
            if not out and not topics:
                raise LogError(f"{path}: not an MCAP file, or torn before any step record ({type(e).__name__}: "
                               f"{e or 'end of file'})") from None
            stopped = f"the file ends in a torn or corrupt record ({type(e).__name__}{': ' + str(e) if str(e) else ''})"
    return _Raw(out, states, stopped)


def robots_in(path: str | Path) -> list[int]:
    """The robots with a step log in the file."""
    return sorted(_raw(Path(path)).steps)


def read_log(path: str | Path, robot: int | None = None) -> RobotLog:
    """Robot ``robot``'s log (None: the file's only robot). LogError (one line) for anything that is not one."""
    path = Path(path)
    got = _raw(path)
    raw = got.steps
    if not raw:
        raise LogError(f"{path}: no step records (/robot_<id>/{steplog.WHAT}): recorded with a stack older than the "
                       "step log, or with --no-record")
    if robot is None:
        if len(raw) > 1:
            raise LogError(f"{path}: step logs of robots {sorted(raw)}: name one (--robot-id N)")
        robot = next(iter(raw))
    if robot not in raw:
        raise LogError(f"{path}: no step log of robot {robot} (robots {sorted(raw)})")
    log = RobotLog(robot, path, [], got.stopped)
    _segments(log, raw[robot], _StateIndex(got.states))
    if not log.segments:
        raise LogError(f"{path}: robot {robot}'s log has no record with its setup (n = 0): the recording began "
                       "after the agent had started")
    return log


class _StateIndex:
    """The recording's states by (id, seq, stamp), decoded once, when a record first names one."""

    def __init__(self, payloads: list[bytes]):
        self.payloads, self._index = payloads, None

    def resolve(self, rec: StepRecord) -> str | None:
        """``rec.states`` from its ``state_refs``; the name of a state the recording lacks, or None."""
        if rec.state_refs is None:
            return None
        if self._index is None:
            self._index = {}
            dec = msgspec.json.Decoder(dict)
            for p in self.payloads:
                doc = dec.decode(p)
                doc = {k: v for k, v in doc.items() if k in STATE_FIELDS}
                doc["situation"] = doc.get("situation") or None
                try:
                    m = msgspec.convert(doc, State)
                except msgspec.ValidationError:
                    continue  # a state written before its seq and stamp were (an older recording)
                self._index[(m.id, m.seq, m.stamp)] = m
        r = rec.state_refs
        states = []
        for key in zip(r.id, r.seq, r.stamp):
            m = self._index.get(key)
            if m is None:
                return f"robot {key[0]}'s state seq {key[1]}"
            states.append(m)
        rec.states, rec.state_refs = states, None
        return None


def _segments(log: RobotLog, payloads: list[tuple[bytes, int]], index: _StateIndex) -> None:
    seg: Segment | None = None
    for i, (payload, ns) in enumerate(payloads):
        try:
            rec = steplog.decode(payload)
        except LogError as e:
            raise LogError(f"{log.path}: robot {log.robot}, record {i}: {e}") from None
        if (missing := index.resolve(rec)) is not None:  # the recorder's queue dropped it: as a gap
            log.stopped = log.stopped or (f"robot {log.robot}'s step {rec.step} took {missing}, which the recording "
                                          "does not have (dropped by its queue): replayed up to there")
            log.skipped += 1
            seg = None
            continue
        if rec.n == 0:  # an agent's first step (a fresh start or a restart), with its setup
            if rec.setup is None:
                raise LogError(f"{log.path}: robot {log.robot}, step {rec.step}: the first record of a life has no setup")
            seg = Segment(rec.setup, [rec], [ns])
            log.segments.append(seg)
            continue
        if seg is None:  # the recording began mid-life, or after a gap: nothing to build the pipeline's state from
            log.skipped += 1
            continue
        last = seg.records[-1]
        if rec.n != last.n + 1:
            log.stopped = log.stopped or (f"a gap in robot {log.robot}'s log after step {last.step} (records "
                                          f"{last.n + 1}..{rec.n - 1} lost on the way): replayed up to there")
            log.skipped += 1
            seg = None
            continue
        seg.records.append(rec)
        seg.stamps.append(ns)
