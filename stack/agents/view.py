"""A robot's own view, recorded (``stack-agent --record FILE``) and/or served live (``stack-agent --viz [EP]``).

What the robot itself knows, per control step: its estimate with its covariance, its scan as received (in
its estimate's frame ``robot_<id>/estimate``: it knows no other), its command, its state, its decision
(situation, policy, where it steers, the mission's goal), the neighbours it heard (their reported states)
and what its radio model dropped this step (per sender: out of range, lost), a scene of all that; its diag;
and events (up, role changes, streams gone stale, robots gone and back, faults, stopped). Topics and schemas:
:mod:`stack.viz.messages` (``AGENT_TOPICS``), the fleet's where they are the same. Times: sim time in
lock-step, wall time (UNIX) in real time: the step's ``now``.

The control loop only takes a snapshot (references to the step's frozen inputs and outputs, a copy of the
covariance block, the neighbour table and the radio's per-sender counters) and queues it: it never blocks;
a full queue drops the step and counts it. One writer thread (:class:`stack.viz.writer.QueuedWriter`)
builds and writes the messages. Imported only when ``--record`` or ``--viz`` is given (the ``viz`` extra).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass

import numpy as np
from foxglove import Channel, Context
from foxglove.channels import FrameTransformsChannel, LaserScanChannel, LogChannel, PoseInFrameChannel, SceneUpdateChannel
from foxglove.messages import Log, LogLevel

from ..comm.messages import Diag
from ..scenario import Scenario
from ..viz import messages as vm
from ..viz.writer import QueuedWriter, SinkConfig
from . import steplog
from .step import StepInputs, StepOutput, StepPipeline

LINK_KEYS = ("delivered", "dropped_range", "dropped_loss")
SCENE_EVERY_S = 1.0  # the scenario's obstacles (the robot's map) are sent again this often


@dataclass(frozen=True)
class StepSnapshot:
    """One control step as the control loop hands it over (nothing in it changes afterwards)."""

    inp: StepInputs
    out: StepOutput
    cmd: tuple[float, float]
    cov: np.ndarray  # 3x3 over (x, y, yaw)
    role: str
    policy: str
    led_since: float | None
    neighbours: tuple  # Neighbour records (replaced, never changed, by the pipeline)
    links: dict[int, dict[str, int]]  # per sender, cumulative
    rejected: int


def snapshot(pl: StepPipeline, inp: StepInputs, out: StepOutput, cmd: tuple[float, float]) -> StepSnapshot:
    """What :class:`AgentView` needs of a step, taken on the control loop (microseconds)."""
    return StepSnapshot(inp=inp, out=out, cmd=cmd, cov=pl.estimator.P[:3, :3], role=pl.role, policy=pl.policy_name,
                        led_since=pl.led_since, neighbours=tuple(pl.neighbours.values()), links=pl.radio.links(),
                        rejected=pl.counters.rejected_states)


class _Channels:
    def __init__(self, ctx: Context, rid: int):
        t = vm.robot_topic
        js = vm.JSON_SCHEMAS | vm.AGENT_SCHEMAS
        self.tf_estimate = FrameTransformsChannel(vm.TOPICS["tf_estimate"], context=ctx)
        self.obstacles = SceneUpdateChannel(vm.TOPICS["obstacles"], context=ctx)
        self.events = LogChannel(vm.TOPICS["events"], context=ctx)
        self.estimate = PoseInFrameChannel(t(rid, "estimate"), context=ctx)
        self.scan = LaserScanChannel(t(rid, "scan"), context=ctx)
        self.scene = SceneUpdateChannel(t(rid, "scene"), context=ctx)
        self.links = SceneUpdateChannel(t(rid, "links"), context=ctx)
        self.step_io = Channel(t(rid, steplog.WHAT), schema=js["step_io"], message_encoding="json", context=ctx)
        self.json = {k: Channel(t(rid, k), schema=js[k], message_encoding="json", context=ctx)
                     for k in ("cmd_vel", "state", "diag", "covariance", "decision", "heard")}

    def close(self) -> None:
        for ch in [self.tf_estimate, self.obstacles, self.events, self.estimate, self.scan, self.scene, self.links,
                   self.step_io, *self.json.values()]:
            ch.close()


class AgentView(QueuedWriter):
    """One robot's view: ``start()``, then :meth:`on_step` / :meth:`on_diag` from the agent, then ``stop()``."""

    def __init__(self, scenario: Scenario, robot_id: int, fleet: str, cfg: SinkConfig, lockstep: bool):
        super().__init__(cfg, server_name=f"stack {fleet} robot {robot_id}")
        self.sc, self.id, self.fleet, self.lockstep = scenario, robot_id, fleet, lockstep
        self.robot = scenario.robot(robot_id)
        f = scenario.formation
        self.goal = tuple(f.goal) if f is not None else (tuple(self.robot.goal) if self.robot.goal else None)
        self.steps = 0  # steps written
        self._ch: _Channels | None = None
        self._links: dict[int, dict[str, int]] = {}  # per sender, cumulative, at the last step written
        self._last: StepSnapshot | None = None
        self._rejected = 0
        self._scene_at: float | None = None
        self._fault = ""

    def start(self) -> "AgentView":
        self.open()
        self.put(("event", time.time_ns() if not self.lockstep else 0, f"robot {self.id}: agent up "
                  f"({self.robot.role or 'peer'}, policy {self.robot.policy}, driver {self.robot.driver})", LogLevel.Info))
        return self

    def stop(self) -> None:
        self.close()

    # --- the control loop's side: queue only ---------------------------------------------------
    def on_step(self, pl: StepPipeline, inp: StepInputs, out: StepOutput, cmd: tuple[float, float]) -> None:
        self.put(("step", snapshot(pl, inp, out, cmd)))

    def on_diag(self, d: Diag) -> None:
        self.put(("diag", d))

    def on_step_io(self, payload: bytes, now: float) -> None:
        """The step's record (``steplog``), already encoded: written as it is."""
        self.put(("step_io", payload, now))

    def open_channels(self, ctx: Context) -> None:
        self._ch = _Channels(ctx, self.id)

    # --- the writer thread -----------------------------------------------------------------------
    def handle(self, kind: str, *rest) -> None:
        if kind == "step":
            self._step(rest[0])
        elif kind == "diag":
            self._diag(rest[0])
        elif kind == "step_io":
            ns = int(round(rest[1] * 1e9))
            self.write(self._ch.step_io, self._topic(steplog.WHAT), rest[0], ns)
        else:
            self.event(*rest)

    def _step(self, s: StepSnapshot) -> None:
        inp, out, p, ch = s.inp, s.out, s.out.pose, self._ch
        ns = int(round(inp.now * 1e9))
        self.broadcast_time(ns)
        self._events(s, ns)
        if self._scene_at is None or inp.t - self._scene_at >= SCENE_EVERY_S - 1e-9:
            self.write(ch.obstacles, vm.TOPICS["obstacles"], vm.obstacles_scene(self.sc, ns), ns)
            self._scene_at = inp.t
        self.write(ch.tf_estimate, vm.TOPICS["tf_estimate"], vm.estimate_frame(self.id, p.x, p.y, p.yaw, ns), ns)
        self.write(ch.estimate, self._topic("estimate"), vm.pose_in_world(p.x, p.y, p.yaw, ns), ns)
        if inp.scan is not None:
            self.write(ch.scan, self._topic("scan"), vm.laser_scan(inp.scan, ns, vm.frame(self.id, estimate=True)), ns)
        self._json("cmd_vel", {"id": self.id, "step": inp.step, "stamp": inp.now, "v": s.cmd[0], "w": s.cmd[1]}, ns)
        state = {"id": self.id, "step": inp.step, "role": s.role, "policy": s.policy, "situation": out.situation,
                 "x": p.x, "y": p.y, "yaw": p.yaw, "v": p.v, "w": p.w, "cov_trace": out.cov_trace}
        if out.d_goal is not None:
            state["d_goal"] = out.d_goal
        self._json("state", state, ns)
        self._json("covariance", _covariance(s, inp), ns)
        self._json("decision", self._decision(s), ns)
        window = self._heard(s, ns)
        where = {self.id: (p.x, p.y)} | {n.id: (n.x, n.y) for n in s.neighbours}
        self.write(ch.links, self._topic("links"), vm.links_scene(window, where, ns), ns)
        self.write(ch.scene, self._topic("scene"), vm.agent_scene(self.id, self.robot.radius, (p.x, p.y, p.yaw), s.cov[:2, :2],
                                                                  out.target, self.goal,
                                                                  [(n.id, n.x, n.y) for n in s.neighbours], ns), ns)
        self.steps += 1
        self._last = s

    def _decision(self, s: StepSnapshot) -> dict:
        doc = {"step": s.inp.step, "t": s.inp.t_run, "role": s.role, "situation": s.out.situation, "policy": s.policy,
               "target": list(s.out.target) if s.out.target is not None else [], "goal": list(self.goal or ()),
               "stale": s.out.stale or ""}
        if s.led_since is not None:
            doc["led_since"] = s.led_since
        return doc

    def _heard(self, s: StepSnapshot, ns: int) -> dict[tuple[int, int], dict[str, int]]:
        """``/robot_<id>/heard`` (the neighbour table, this step's radio outcomes per sender); the links' window."""
        window = {}
        for sender, now in s.links.items():
            before = self._links.get(sender, dict.fromkeys(LINK_KEYS, 0))
            window[(sender, self.id)] = {k: max(now[k] - before[k], 0) for k in LINK_KEYS}
        self._links = s.links
        totals = {k: sum(c[k] for c in window.values()) for k in LINK_KEYS}
        neighbours = [{"id": n.id, "role": n.role, "x": n.x, "y": n.y, "yaw": n.yaw, "v": n.v, "w": n.w,
                       "age": s.inp.now - n.stamp} for n in s.neighbours]
        self._json("heard", {"step": s.inp.step, "t": s.inp.t_run, "neighbours": neighbours, "gone": sorted(s.inp.dead),
                             **totals, "rejected": s.rejected - self._rejected,
                             "links": {str(snd): c for (snd, _), c in window.items() if any(c.values())}}, ns)
        self._rejected = s.rejected
        return window

    def _events(self, s: StepSnapshot, ns: int) -> None:
        """What changed since the last step: role (failover), a stale stream, robots gone or back."""
        last = self._last
        if last is None:
            return
        t = s.inp.t_run
        if s.role != last.role:
            self.event(ns, f"robot {self.id}: now {s.role} (was {last.role}) at t={t:.1f} s: failover", LogLevel.Warning)
        if s.out.stale != last.out.stale:
            self.event(ns, f"robot {self.id}: {s.out.stale} stale: zero velocity" if s.out.stale else
                       f"robot {self.id}: {last.out.stale} back", LogLevel.Warning if s.out.stale else LogLevel.Info)
        for rid in sorted(s.inp.dead - last.inp.dead - {self.id}):
            self.event(ns, f"robot {self.id}: robot {rid} gone at t={t:.1f} s", LogLevel.Warning)
        for rid in sorted(last.inp.dead - s.inp.dead - {self.id}):
            self.event(ns, f"robot {self.id}: robot {rid} back at t={t:.1f} s")

    def _diag(self, d: Diag) -> None:
        ns = int(round(d.stamp * 1e9))
        self._json("diag", vm.diag_doc(d), ns)
        if d.fault and d.fault != self._fault:
            self.event(ns, f"robot {self.id}: fault: {d.fault}", LogLevel.Error)
        self._fault = d.fault
        if d.state == "stopped":
            self.event(ns, f"robot {self.id}: stopped (zero velocity) after step {d.step}")

    def finish(self) -> None:
        dropped = self.dropped_now()
        level = LogLevel.Warning if dropped or self.malformed else LogLevel.Info
        self.event(self.last_ns, f"robot {self.id} view: {self.steps} steps, {sum(self.counts.values())} messages "
                                 f"written, {dropped} dropped (queue full), {self.malformed} malformed", level)
        self.write_metadata("stack.agent", {
            "scenario": self.sc.name, "fleet": self.fleet, "robot": str(self.id), "role": self.robot.role or "peer",
            "policy": self.robot.policy, "driver": self.robot.driver, "time": "sim" if self.lockstep else "wall",
            "steps": str(self.steps), "dropped": str(dropped), "malformed": str(self.malformed),
            "queue_size": str(self.cfg.queue_size), "counts": json.dumps(self.counts), "writer_cpu_s": f"{self.cpu_s():.3f}"})
        self.attach("scenario.yaml", "application/yaml", self.sc.to_yaml().encode(), time.time_ns())
        self._ch.close()

    # --- helpers ------------------------------------------------------------------------------------
    def _topic(self, what: str) -> str:
        return vm.robot_topic(self.id, what)

    def _json(self, what: str, doc: dict, ns: int) -> None:
        self.write(self._ch.json[what], self._topic(what), doc, ns)

    def event(self, ns: int, text: str, level=LogLevel.Info) -> None:
        self.write(self._ch.events, vm.TOPICS["events"], Log(timestamp=vm.ts(ns), level=level, message=text,
                                                            name=f"robot_{self.id}", file="", line=0), ns)


def _covariance(s: StepSnapshot, inp: StepInputs) -> dict:
    c = s.cov
    return {"step": inp.step, "t": inp.t_run, "cov": [float(v) for v in c.ravel()],
            "sigma_x": math.sqrt(max(c[0, 0], 0.0)), "sigma_y": math.sqrt(max(c[1, 1], 0.0)),
            "sigma_yaw": math.sqrt(max(c[2, 2], 0.0)), "cov_trace": s.out.cov_trace}


def start_view(cfg) -> AgentView | None:
    """The view an :class:`~stack.agents.agent.AgentConfig` asks for (``record`` and/or ``viz``), started; None if neither.
    RecorderError (one line) if the file or the port cannot be opened."""
    if cfg.record is None and cfg.viz is None:
        return None
    from pathlib import Path

    sink = SinkConfig(out=Path(cfg.record) if cfg.record else None, viz=cfg.viz, allow_remote=cfg.allow_remote)
    return AgentView(cfg.scenario, cfg.robot_id, cfg.fleet, sink, lockstep=cfg.lockstep).start()
