"""Record a fleet to MCAP (``run.mcap``) and serve the same channels live (Foxglove WebSocket protocol).

The :class:`Recorder` only listens: on an open Zenoh session it subscribes to what already crosses
a fleet (world clock, truth, status and fault requests; each robot's scan, state, command and diag;
the agents' liveliness) and writes Foxglove messages (:mod:`.viz_messages`) with the Foxglove SDK,
to a file (``foxglove.open_mcap``) and/or a live server (``foxglove.start_server``), both sinks of one
SDK context, so the live view and the recording carry the same channels (the sinks, the queue and the
writer thread: :mod:`stack.viz.writer`, shared with a robot's own view).

Writing never blocks a Zenoh callback (nor the control loops behind it): callbacks only enqueue the
raw payload; one writer thread decodes, converts and logs. The queue is bounded; a sample that finds
it full is dropped and counted (the recording's metadata and its last ``/events`` line say how many).

Times: sim time (from 0) in lock-step, wall time (UNIX) in real time, as the world's clock says.

Also a tool of its own, to record any fleet from any host (hardware too)::

    python -m stack.fleet.record --connect tcp/127.0.0.1:7447 --fleet NAME --scenario FILE --out DIR [--viz]
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh
from foxglove import Channel, Context
from foxglove.channels import FrameTransformsChannel, LaserScanChannel, LogChannel, PoseInFrameChannel, SceneUpdateChannel
from foxglove.messages import Log, LogLevel

from ..comm import Keys, MessageError, decode
from ..comm.messages import Clock, CmdVel, Diag, FaultAck, FaultRequest, Scan, State, Truth, WorldStatus
from ..agents import steplog
from ..agents.steplog import WHAT as STEP_IO
from ..scenario import Scenario
from ..viz.endpoint import DEFAULT_VIZ, parse_viz_endpoint  # noqa: F401 - the fleet's CLI and tests use them from here
from ..viz.writer import COMPRESSION, QueuedWriter, RecorderError, SinkConfig  # noqa: F401
from . import viz_messages as vm
from .viz_handlers import HANDLERS

log = logging.getLogger("stack.record")

_WORLD_KINDS = {"clock": Clock, "truth": Truth, "status": WorldStatus, "fault": FaultRequest, "fault_ack": FaultAck}


class _RecordedScan(Scan):
    """A scan as the recorder decodes it: :class:`~stack.comm.messages.Scan`'s fields and types, without its
    per-beam range check (the agents do that; here it would cost more than the rest of the recording)."""

    def __post_init__(self) -> None:
        pass


_ROBOT_KINDS = {"scan": _RecordedScan, "state": State, "cmd_vel": CmdVel, "diag": Diag, "virtual_scan": _RecordedScan}


@dataclass
class RecorderConfig(SinkConfig):
    """One recording of one fleet (where it goes: :class:`~stack.viz.writer.SinkConfig`)."""

    realtime: bool | None = None
    """Stamp with wall time (True) or sim time (False); None: as the world's first clock says."""
    links_window_steps: int = 10
    """The comm graph is drawn once per this many steps (the agents' diag period), from the counts of the last window."""
    scene_every_s: float = 1.0
    """The obstacles' scene is sent again this often (live clients that join late, players that seek)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.links_window_steps < 1 or not self.scene_every_s > 0:
            raise ValueError("recorder: queue_size and links_window_steps must be >= 1, scene_every_s > 0")


class _Channels:
    """Every channel of a recording, on one SDK context (see :data:`.viz_messages.TOPICS`)."""

    def __init__(self, ctx: Context, ids: list[int], virtual: set[int] | frozenset[int] = frozenset()):
        t, js = vm.TOPICS, vm.JSON_SCHEMAS
        self.clock = Channel(t["clock"], schema=js["clock"], message_encoding="json", context=ctx)
        self.metrics = Channel(t["metrics"], schema=js["metrics"], message_encoding="json", context=ctx)
        self.tf = FrameTransformsChannel(t["tf"], context=ctx)
        self.tf_estimate = FrameTransformsChannel(t["tf_estimate"], context=ctx)
        self.obstacles = SceneUpdateChannel(t["obstacles"], context=ctx)
        self.robots = SceneUpdateChannel(t["robots"], context=ctx)
        self.slots = SceneUpdateChannel(t["slots"], context=ctx)
        self.links = SceneUpdateChannel(t["links"], context=ctx)
        self.events = LogChannel(t["events"], context=ctx)
        self.robot = {rid: {
            "pose": PoseInFrameChannel(vm.robot_topic(rid, "pose"), context=ctx),
            "estimate": PoseInFrameChannel(vm.robot_topic(rid, "estimate"), context=ctx),
            "scan": LaserScanChannel(vm.robot_topic(rid, "scan"), context=ctx),
            **{k: Channel(vm.robot_topic(rid, k), schema=js[k], message_encoding="json", context=ctx)
               for k in ("cmd_vel", "state", "diag", STEP_IO)},
            **({"virtual_scan": LaserScanChannel(vm.robot_topic(rid, "virtual_scan"), context=ctx)} if rid in virtual
               else {}),  # a real robot's virtual returns, apart from its own scan
        } for rid in ids}

    def close(self) -> None:
        for ch in [self.clock, self.metrics, self.tf, self.tf_estimate, self.obstacles, self.robots, self.slots,
                   self.links, self.events] + [c for per in self.robot.values() for c in per.values()]:
            ch.close()


class Recorder(QueuedWriter):
    """Listens to one fleet and writes/serves it; ``start()`` then ``stop()`` (or a ``with`` block)."""

    def __init__(self, session: zenoh.Session, keys: Keys, scenario: Scenario, cfg: RecorderConfig):
        super().__init__(cfg, server_name=f"stack {keys.fleet}")
        self.s, self.keys, self.sc = session, keys, scenario
        self.ids = list(scenario.ids)
        self.realtime = cfg.realtime
        self.done = threading.Event()  # the world said it is done
        self._subs: list = []
        self._ch = None
        self._pending: list = []  # samples before the first clock, while the time base is unknown
        self._view = _View()
        self.step_logs: dict[int, Path] = {}  # robot -> its agent's --step-log file, written in at the end

    # --- life cycle ------------------------------------------------------------------
    def start(self) -> "Recorder":
        self.open()
        self._subscribe()
        return self

    def open_channels(self, ctx: Context) -> None:
        self._ch = _Channels(ctx, self.ids, {r.id for r in self.sc.robots if r.embodiment == "real" and r.lidar.virtual})

    def _subscribe(self) -> None:
        k, s = self.keys, self.s
        self._subs = [s.declare_subscriber(k.world(name), self._enqueue(name)) for name in _WORLD_KINDS]
        self._subs += [s.declare_subscriber(k.all_robots(name), self._enqueue(name)) for name in (*_ROBOT_KINDS, STEP_IO)]
        self._subs.append(s.liveliness().declare_subscriber(k.all_alive, self._on_alive, history=True))

    def stop(self) -> None:
        """Stop listening, write what is queued, the closing events and metadata; close the file and server."""
        for sub in self._subs:
            sub.undeclare()
        self._subs = []
        self.close()

    def __enter__(self) -> "Recorder":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # --- Zenoh callbacks: enqueue only --------------------------------------------------
    def _enqueue(self, kind: str):
        def callback(sample: zenoh.Sample) -> None:
            self.put((kind, str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))
        return callback

    def _on_alive(self, sample: zenoh.Sample) -> None:
        left = sample.kind == zenoh.SampleKind.DELETE
        self.put(("alive", str(sample.key_expr), left, time.time_ns()))

    _put = QueuedWriter.put

    # --- the writer thread ---------------------------------------------------------------
    def handle(self, kind: str, key: str, payload, recv_ns: int) -> None:
        if kind == "alive":
            msg = payload
        elif kind == STEP_IO:  # written as it came (JSON); only its head is read, to place it
            try:
                msg = (steplog.head(payload), payload)
            except steplog.LogError:
                self.malformed += 1
                return
            if msg[0].id not in self._ch.robot or Keys.id_of(key) != msg[0].id:
                self.malformed += 1
                return
        else:
            try:
                msg = decode(payload, _WORLD_KINDS.get(kind) or _ROBOT_KINDS[kind])
            except MessageError:
                self.malformed += 1
                return
            if kind in _ROBOT_KINDS and (msg.id not in self._ch.robot or Keys.id_of(key) != msg.id
                                         or kind not in self._ch.robot[msg.id] and kind in vm.ROBOT_TOPICS):
                self.malformed += 1
                return
        if self.realtime is None:
            if kind != "clock":
                if len(self._pending) < self.cfg.queue_size:
                    self._pending.append((kind, key, msg, recv_ns))
                else:
                    self.dropped += 1
                return
            self.realtime = not msg.lockstep
            for p in self._pending:
                _dispatch(self, *p)
            self._pending = []
        _dispatch(self, kind, key, msg, recv_ns)

    def finish(self) -> None:
        if self.realtime is None:  # never heard a clock: what came is stamped as lock-step (sim time 0)
            self.realtime = False
            for p in self._pending:
                _dispatch(self, *p)
        self._step_logs_in()
        dropped = self.dropped_now()
        level = LogLevel.Warning if dropped or self.malformed else LogLevel.Info
        self.event(self.last_ns, f"recorder: {sum(self.counts.values())} messages written, {dropped} dropped "
                                 f"(queue full), {self.malformed} malformed", level)
        self.write_metadata("stack.run", {
            "scenario": self.sc.name, "fleet": self.keys.fleet, "robots": json.dumps(self.ids),
            "time": "wall" if self.realtime else "sim", "dropped": str(dropped), "malformed": str(self.malformed),
            "queue_size": str(self.cfg.queue_size), "counts": json.dumps(self.counts), "writer_cpu_s": f"{self.cpu_s():.3f}"})
        self.attach("scenario.yaml", "application/yaml", self.sc.to_yaml().encode(), time.time_ns())
        self._ch.close()

    def _step_logs_in(self) -> None:
        """Each agent's step-log file (``stack-agent --step-log``) into its ``/robot_<id>/step_io`` channel, at each
        record's own time, then removes the file; a line that does not decode (a killed agent's torn last one) is counted
        as malformed."""
        for rid, path in sorted(self.step_logs.items()):
            if rid not in self._ch.robot or not path.exists():
                continue
            with path.open("rb") as f:
                for line in f:
                    try:
                        head = steplog.head(line.rstrip(b"\n"))
                    except steplog.LogError:
                        self.malformed += 1
                        continue
                    if head.id != rid:
                        self.malformed += 1
                        continue
                    ns = int(round((head.t if not self.realtime else head.now) * 1e9))
                    self.write(self._ch.robot[rid][STEP_IO], vm.robot_topic(rid, STEP_IO), line.rstrip(b"\n"), ns)
            path.unlink()  # the recording has them now

    # --- what the handlers use -------------------------------------------------------------
    def stamp(self, sim_t: float, recv_ns: int) -> int:
        """A message's time: its sim time in lock-step, the wall time it arrived in real time."""
        return recv_ns if self.realtime else int(round(sim_t * 1e9))

    def event(self, ns: int, text: str, level=LogLevel.Info) -> None:
        self.write(self._ch.events, vm.TOPICS["events"], Log(timestamp=vm.ts(ns), level=level, message=text,
                                                            name="fleet", file="", line=0), ns)


class _View:
    """What the writer thread remembers between messages: the fleet as it last saw it."""

    def __init__(self):
        self.t = 0.0
        self.step = -1
        self.dead: set[int] = set()
        self.where: dict[int, tuple[float, float]] = {}  # true positions
        self.estimates: dict[int, State] = {}
        self.roles: dict[int, str] = {}
        self.faults: dict[int, str] = {}
        self.links_total: dict[tuple[int, int], dict[str, int]] = {}  # (sender, receiver) -> cumulative counts
        self.links_window: dict[tuple[int, int], dict[str, int]] = {}  # the last window's counts
        self.scene_at: float | None = None
        self.stale: set[int] = set()  # real robots whose pose source is stale


def _dispatch(rec: Recorder, kind: str, key: str, msg, recv_ns: int) -> None:
    HANDLERS[kind](rec, rec._ch, rec._view, key, msg, recv_ns)


def parser():
    import argparse

    ap = argparse.ArgumentParser(prog="python -m stack.fleet.record",
                                 description="Record a running fleet to run.mcap (and serve it live); ends when its world is done.")
    ap.add_argument("--connect", required=True, metavar="EP", help="the fleet's Zenoh router, e.g. tcp/127.0.0.1:7447")
    ap.add_argument("--fleet", required=True, help="fleet name (key prefix stack/<fleet>/)")
    ap.add_argument("--scenario", required=True, type=Path, help="the fleet's scenario YAML")
    ap.add_argument("--out", type=Path, help="folder for run.mcap (default: live view only)")
    ap.add_argument("--viz", nargs="?", const=DEFAULT_VIZ, metavar="EP", help=f"serve live (default {DEFAULT_VIZ})")
    ap.add_argument("--allow-remote", action="store_true", help="router or live endpoint off loopback")
    ap.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config (deploy/)")
    ap.add_argument("--compression", choices=sorted(COMPRESSION), default="zstd")
    ap.add_argument("--wait", type=float, default=30.0, metavar="S", help="how long to try to reach the router")
    return ap


def _session(a):
    from ..comm.session import SessionConfig, SessionError, open_session

    cfg = SessionConfig(connect=a.connect.split(","), config_file=a.zenoh_config, allow_remote=a.allow_remote)
    deadline = time.monotonic() + a.wait
    while True:
        try:
            return open_session(cfg)
        except SessionError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def main(argv: list[str] | None = None) -> int:
    """Record until the world says it is done (then 1 s more, for the agents' last words) or SIGINT/SIGTERM."""
    import signal
    import sys

    from ..comm.session import SessionError
    from ..scenario import ScenarioError, load_scenario

    a = parser().parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        sc = load_scenario(a.scenario)
        cfg = RecorderConfig(out=a.out / "run.mcap" if a.out else None, viz=a.viz, allow_remote=a.allow_remote,
                             compression=a.compression)
        session = _session(a)
    except (ScenarioError, ValueError, SessionError) as e:
        print(f"record: {e}", file=sys.stderr)
        return 2
    with session:
        try:
            rec = Recorder(session, Keys(a.fleet), sc, cfg).start()
        except RecorderError as e:
            print(str(e), file=sys.stderr)
            return 2
        print(f"recording fleet {a.fleet!r}" + (f" to {cfg.out}" if cfg.out else "")
              + (f", live on ws://{parse_viz_endpoint(a.viz, a.allow_remote)[0]}:{rec.port}" if a.viz else ""), flush=True)
        try:
            while not stop.is_set() and not rec.done.wait(0.2):
                pass
            stop.wait(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            rec.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
