"""``stack-fleet run``: a Zenoh router on loopback, the world, one ``stack-agent`` process per robot.

A :class:`Fleet` has an explicit lifecycle: ``start`` (router, our session, world, agents),
``serve`` (watch the world's clock and status and the agents' diag and state; do the
``--kill``/``--freeze``/``--restart`` faults the world asks for; notice crashes), then
``stop`` (agents first: SIGTERM -> their zero commands; then the world; then the router), on
every path: the end, a start that failed, an error, Ctrl-C or SIGTERM. ``run_fleet`` runs
one and writes ``report.json`` and the plots.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import zenoh

from ..comm import Keys, encode
from ..comm.messages import FaultAck, FaultRequest
from ..comm.session import SessionConfig, SessionError, free_tcp_endpoint, open_session
from ..scenario import Scenario, with_driver_settings, with_lidar_settings
from .monitor import Monitor
from .procs import Proc, stop_all, wait_port
from .report import build_report

log = logging.getLogger("stack.fleet")

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_CRASH = 0, 1, 2, 3
ZENOH_RUNTIME = "(app: (worker_threads: 1), tx: (handover: app), rx: (handover: app), acc: (handover: app), net: (handover: app))"
FAULT_DONE = {"kill": "killed", "freeze": "frozen", "restart": "restarted"}
"""A fault the world asks for -> its kind in the report's ``faults``."""


@dataclass
class FleetConfig:
    """One simulated fleet run."""

    scenario: Scenario
    """Validated scenario with the command line's overrides applied."""
    out: Path
    """Folder for report.json, plots, logs and the resolved scenario."""
    realtime: bool = False
    """Run the world on the wall clock instead of lock-step."""
    gui: bool = False
    """Open pybullet's GUI."""
    listen: str | None = None
    """Router endpoint; a free loopback port when None."""
    faults: list[tuple[str, int, float]] = field(default_factory=list)
    """(kind, robot id, sim time): ``kill`` (SIGKILL the agent), ``freeze`` (SIGSTOP it), ``restart``
    (start it again). The world asks for each at the first step at or after its time and waits
    until it is done, so lock-step runs with faults are repeatable."""
    can_log: bool = False
    """Every CAN robot's driver logs its bus to ``logs/can-<id>.asc`` (python-can ``can.Logger``)."""
    device_faults: list[tuple[int, float]] = field(default_factory=list)
    """(robot id, sim time): that robot's simulated device fails (the world does it; the driver must notice)."""
    fleet: str | None = None
    """Fleet name (key prefix); derived from the out folder when None."""
    progress: bool = True
    """Show a live progress line on stderr."""
    wall_timeout_s: float | None = None
    """Give up after this much wall time (default: generous, from the duration)."""
    plots: bool = True
    """Write trajectories.png and distances.png."""
    connect: str | None = None
    """An existing router to join (a site router, multi-host); none is started then."""
    external_agents: bool = False
    """The agents run elsewhere (their own machines): start none, wait for their liveliness tokens."""
    wait_agents_s: float = 60.0
    """How long to wait for every expected agent's token."""
    rejoin_wait_s: float = 10.0
    """Real time: how long a robot out of contact may take to come back before the world calls it gone."""
    lockstep_timeout_s: float = 2.0
    """Lock-step: how long (wall) the world waits for an agent's command before it takes the step without it."""
    zenoh_config: str | None = None
    """A zenoh json5 file (deploy/: TLS, access control) for our own session and the world's."""
    allow_remote: bool = False
    """Allow router endpoints off loopback (multi-host)."""
    record: bool = True
    """Write ``run.mcap`` (Foxglove schemas; ``stack.fleet.record``) and, with ``plots``, ``replay.gif``."""
    viz: str | None = None
    """Serve the recording's channels live (Foxglove WebSocket) on this ``tcp/HOST:PORT``; None: no live view."""


RUN_OUTPUTS = ("report.json", "truth.npz", "world.json", "devices.json", "scenario.agents.yaml", "trajectories.png",
               "distances.png", "errors.png", "run.mcap", "replay.gif")
"""What a run writes into its folder (besides ``logs/`` and the resolved scenario)."""


def sigterm_as_interrupt() -> None:
    """SIGTERM tears a fleet down in order (agents' zero commands first), exactly like Ctrl-C."""
    def on_term(signum, _frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)


def _agents_scenario(sc: Scenario, out: Path, world: Proc, timeout: float = 30.0, can_log: bool = False) -> Path:
    """Wait for the world's ``devices.json`` and write the scenario the agents read: the resolved one
    with each hosted robot's driver settings pointing at its simulated device (pty, UDP port, keys),
    and (``can_log``) each CAN robot's bus log in ``logs/``."""
    path = out / "devices.json"
    deadline = time.monotonic() + timeout
    while not path.exists():
        if world.poll() is not None:
            raise TimeoutError(f"the world exited with code {world.poll()} before its simulated devices were up")
        if time.monotonic() > deadline:
            raise TimeoutError(f"the world did not bring up its simulated devices within {timeout:.0f} s")
        time.sleep(0.05)
    devices = json.loads(path.read_text())
    settings = {int(rid): dict(d["settings"]) for rid, d in devices.items() if "settings" in d}
    lidars = {int(rid): dict(d["lidar"]["settings"]) for rid, d in devices.items() if "lidar" in d}
    if can_log:
        from ..drivers import DRIVERS

        for r in sc.robots:  # every robot whose driver logs a CAN bus (its config has ``can_log``)
            cls = DRIVERS[r.driver].config_class()
            if cls is not None and "can_log" in {f.name for f in fields(cls)}:
                settings[r.id]["can_log"] = str(out / "logs" / f"can-{r.id}.asc")
    agents = with_lidar_settings(with_driver_settings(sc, settings), lidars)
    target = out / "scenario.agents.yaml"
    target.write_text(agents.to_yaml())
    return target


class _Abort(Exception):
    """The fleet could not start; ``crashed`` says why and the report shows it."""


class Fleet:
    """One simulated fleet run: ``start``, ``serve``, ``stop`` (:meth:`run` does all three and the report).

    ``spawn(name, argv, log_path, env)`` starts one child process (:class:`~.procs.Proc`; tests pass their own).
    """

    def __init__(self, cfg: FleetConfig, spawn=Proc):
        self.cfg, self.sc, self.out = cfg, cfg.scenario, cfg.out
        self.fleet = cfg.fleet or f"run{os.getpid()}"
        self.keys = Keys(self.fleet)
        self.endpoint = cfg.connect or cfg.listen or free_tcp_endpoint()
        self.env = dict(os.environ, PYTHONUNBUFFERED="1")
        # many small processes on few cores: one zenoh worker thread each (fleet_bench: +15 % steps/s at 32 robots)
        self.env.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
        self.spawn = spawn
        self.resolved = self.out / "scenario.resolved.yaml"
        self.agents_scenario = self.resolved
        self.router: Proc | None = None
        self.procs: dict[str, Proc] = {}  # "world", "agent-<id>": the ones running now (or that ended)
        self.retired: list[Proc] = []  # agents replaced by a restart (and routers that died under the run)
        self.router_restarts: list[dict] = []  # our own router died under the run and was started again
        self.faults: list[dict] = []
        self.crashed: list[dict] = []
        self.session: zenoh.Session | None = None
        self.mon: Monitor | None = None
        self.recorder = None
        self.ack_pub = None
        self.diags: dict = {}
        self.estimates: dict = {}
        self.wanted = {(kind, rid): at for kind, rid, at in cfg.faults}
        self.wall0 = time.monotonic()
        self.wall_limit = cfg.wall_timeout_s or max(120.0, self.sc.duration * (3.0 if cfg.realtime else 2.0) + 60.0)
        self._remote = ["--allow-remote"] if cfg.allow_remote else []
        self._zconf = ["--zenoh-config", cfg.zenoh_config] if cfg.zenoh_config else []

    # --- start -----------------------------------------------------------------------------------

    def start(self) -> None:
        """The run's folder, the router (unless joining one), our session, the world, the agents;
        raises :class:`_Abort` (with ``crashed`` saying why) if any of them cannot start."""
        (self.out / "logs").mkdir(parents=True, exist_ok=True)
        for name in RUN_OUTPUTS:  # a folder used before: nothing of that run may pass for this one's
            (self.out / name).unlink(missing_ok=True)
        self.resolved.write_text(self.sc.to_yaml())
        self._start_router()
        try:
            self.session = open_session(SessionConfig(mode="client", connect=self.endpoint.split(","),
                                                      config_file=self.cfg.zenoh_config,
                                                      allow_remote=self.cfg.allow_remote))
        except SessionError as e:
            self._abort("orchestrator", None, str(e))
        self.mon = Monitor(self.session, self.keys)
        self._start_recorder()
        self._start_world()
        self._start_agents()
        self.ack_pub = self.session.declare_publisher(self.keys.world("fault_ack"),
                                                      congestion_control=zenoh.CongestionControl.BLOCK)

    def _start_recorder(self) -> None:
        """The recording (and the live view) listen on our session from before the world's first step."""
        cfg = self.cfg
        if not (cfg.record or cfg.viz):
            return
        from .record import Recorder, RecorderConfig, RecorderError

        try:
            self.recorder = Recorder(self.session, self.keys, self.sc, RecorderConfig(
                out=self.out / "run.mcap" if cfg.record else None, viz=cfg.viz, allow_remote=cfg.allow_remote,
                realtime=cfg.realtime)).start()
        except (RecorderError, ValueError) as e:
            self._abort("recorder", None, str(e))

    def _stop_recorder(self) -> None:
        if self.recorder is not None:
            self.recorder.stop()
            self.recorder = None

    def _abort(self, process: str, exit_code: int | None, why: str) -> None:
        self.crashed.append({"process": process, "exit_code": exit_code, "sim_time_s": 0.0, "log_tail": why})
        raise _Abort

    def _start_router(self, log_name: str = "router.log") -> None:
        if self.cfg.connect is not None:
            return
        argv = [sys.executable, "-m", "stack.comm.router", "--listen", self.endpoint, *self._remote]
        if self.cfg.zenoh_config:
            argv += ["--config", self.cfg.zenoh_config]
        self.router = self.spawn("router", argv, self.out / "logs" / log_name, self.env)
        try:
            wait_port(self.endpoint, process=self.router)
        except TimeoutError as e:
            self._abort("router", self.router.poll(), f"{e}: {self.router.tail(2)}")

    def _start_world(self) -> None:
        cfg = self.cfg
        argv = [sys.executable, "-m", "stack.sim_bridge", "--scenario", str(self.resolved), "--connect", self.endpoint,
                "--fleet", self.fleet, "--out", str(self.out), "--wait-agents", f"{cfg.wait_agents_s:g}",
                "--rejoin-wait", f"{cfg.rejoin_wait_s:g}",
                "--lockstep-timeout", f"{cfg.lockstep_timeout_s:g}",
                *self._remote, *self._zconf]
        if cfg.realtime:
            argv.append("--realtime")
            if cfg.external_agents:  # not ours to stop: a real-time agent stays up when the run ends (its
                argv += ["--linger", "2"]  # diag, once a second, gets two periods to bring its last word)
        if cfg.gui:
            argv.append("--gui")
        for kind, rid, at in cfg.faults:
            argv += ["--" + kind, f"{rid}@{at:g}"]
        for rid, at in cfg.device_faults:
            argv += ["--device-fault", f"{rid}@{at:g}"]
        world = self.procs["world"] = self.spawn("world", argv, self.out / "logs" / "world.log", self.env)
        if any(r.driver != "sim" for r in self.sc.robots) and not cfg.external_agents:
            # robots on simulated hardware: their drivers go where the world put each device
            try:
                self.agents_scenario = _agents_scenario(self.sc, self.out, world, can_log=cfg.can_log)
            except TimeoutError as e:
                self._abort("world", world.poll(), f"{e}: {world.tail(3)}")

    def _start_agents(self) -> None:
        """An agent for every simulated robot (none with ``external_agents``); then wait for the tokens of the
        agents that run elsewhere: every real robot's (on the robot), all of them with ``external_agents``."""
        real = {r.id for r in self.sc.robots if r.embodiment == "real"}
        if not self.cfg.external_agents:
            for r in self.sc.robots:
                if r.id not in real:
                    self.procs[f"agent-{r.id}"] = self._start_agent(r.id, f"agent-{r.id}.log")
        elsewhere = set(self.sc.ids) if self.cfg.external_agents else real
        if real:
            log.warning("fleet: waiting for the real robots' agents %s: on each robot, stack-agent --id N --scenario "
                        "%s --connect %s --fleet %s", sorted(real), self.agents_scenario, self.endpoint, self.fleet)
        missing = self.mon.wait_alive(elsewhere, self.cfg.wait_agents_s) if elsewhere else set()
        if missing:
            self._abort("agents", None, f"robots {sorted(missing)} never came up on {self.endpoint} (fleet "
                                        f"{self.fleet!r}) within {self.cfg.wait_agents_s:g} s")

    def _start_agent(self, rid: int, log_name: str) -> Proc:
        r = self.sc.robot(rid)
        argv = [sys.executable, "-m", "stack.agents", "--id", str(r.id), "--scenario", str(self.agents_scenario),
                "--connect", self.endpoint, "--fleet", self.fleet, "--log-level", "INFO", *self._remote, *self._zconf]
        if r.role:
            argv += ["--role", r.role]
        if not self.cfg.realtime:
            argv.append("--lockstep")
        if self.cfg.record and self.recorder is not None:  # every step's inputs in run.mcap (stack-replay): a file
            path = self.out / "logs" / f"steps-{rid}.jsonl"  # each, read by the recorder at the end (not over Zenoh)
            if rid not in self.recorder.step_logs:  # a restart appends (its life starts again at n = 0)
                path.unlink(missing_ok=True)  # an earlier run's in the same folder does not
            self.recorder.step_logs[rid] = path
            argv += ["--step-log", str(path)]
        return self.spawn(f"agent {r.id}", argv, self.out / "logs" / log_name, self.env)

    # --- serve -----------------------------------------------------------------------------------

    def serve(self) -> None:
        """Watch the run until the world is done or gone (or the wall-time limit), then wind it down."""
        progress = _Progress(self.sc, enabled=self.cfg.progress)
        try:
            while not self.tick(progress):
                pass
        finally:
            progress.close()
        self._wind_down()

    def tick(self, progress: "_Progress | None" = None) -> bool:
        """One look at the run (every 50 ms): answer the world's fault requests, notice crashes;
        True when the run is over."""
        time.sleep(0.05)
        t, status, requests = self.mon.take()
        if progress is not None:
            progress.update(t, time.monotonic() - self.wall0)
        for req in requests:  # the world asks, we do, we answer (it waits for the answer)
            done = [rid for rid in req.ids if self.do_fault(req, rid)]
            self.ack_pub.put(encode(FaultAck(step=req.step, kind=req.kind, done=done)))
        self.note_crashes(t, status)
        self._router_watch(t)
        if status == "done" or self.procs["world"].poll() is not None:
            return True
        if time.monotonic() - self.wall0 > self.wall_limit:
            self.crashed.append({"process": "world", "exit_code": None, "sim_time_s": t,
                                 "log_tail": f"no end after {self.wall_limit:.0f} s wall time"})
            return True
        return False

    def _router_watch(self, t: float) -> None:
        """Our own router died under the run (nothing of ours stops it before the end): start it again on the
        same endpoint, as a site's service manager would; the sessions rejoin it (``docs/network-faults.md``)."""
        r = self.router
        if r is None or r.asked_to_stop or r.poll() is None:
            return
        log.warning("fleet: t=%.1f s: the router exited (code %s): starting it again on %s", t, r.poll(), self.endpoint)
        self.router_restarts.append({"sim_time_s": round(t, 3), "exit_code": r.poll()})
        self.retired.append(r)
        self._start_router(f"router.restart{len(self.router_restarts)}.log")

    def do_fault(self, req: FaultRequest, rid: int) -> bool:
        """Do one fault the world asked for (one we were told to inject); whether it was done."""
        name = f"agent-{rid}"
        if name not in self.procs or (req.kind, rid) not in self.wanted or req.kind not in FAULT_DONE:
            return False
        pr = self.procs[name]
        if req.kind == "kill":
            pr.killed_at = req.t
            pr.kill()
        elif req.kind == "freeze":
            pr.frozen = True
            pr.signal(signal.SIGSTOP)
        else:  # restart: a still running one (e.g. frozen) goes first
            if pr.poll() is None:
                pr.killed_at = req.t
                pr.kill()
            self.retired.append(pr)
            n = sum(1 for x in self.retired if x.name == pr.name)
            self.procs[name] = self._start_agent(rid, f"agent-{rid}.restart{n}.log")
        self.faults.append({"robot": rid, "kind": FAULT_DONE[req.kind], "at_s": self.wanted[(req.kind, rid)],
                            "sim_time_s": req.t, "step": req.step})
        return True

    def note_crashes(self, t: float, status: str) -> None:
        """Every agent that ended by itself before the world was done (not killed, not stopped by us) crashed.
        A lock-step agent ends with code 0 once the world is done: that news gets 2 s to arrive here."""
        for name, pr in self.procs.items():
            rc = pr.poll()
            if rc == 0 and status != "done":
                pr.exited_at = pr.exited_at or time.monotonic()
                if time.monotonic() - pr.exited_at < 2.0:
                    continue
            if rc is not None and not pr.asked_to_stop and pr.killed_at is None and name != "world" \
                    and status != "done" and not self._crashed(pr):
                self.crashed.append({"process": pr.name, "exit_code": rc, "sim_time_s": t, "log_tail": pr.tail()})
                self.faults.append({"robot": int(name.split("-")[1]), "kind": "crashed", "exit_code": rc,
                                    "sim_time_s": t})

    def _crashed(self, pr: Proc) -> bool:
        return any(c["process"] == pr.name for c in self.crashed)

    def _agents(self) -> list[Proc]:
        return [pr for name, pr in self.procs.items() if name.startswith("agent-")]

    def _wind_down(self) -> None:
        """The run is over: agents first (10 s each to command zero and leave), then the world (15 s to write
        its log); any that ended badly crashed. Then what the agents said (diag, estimates)."""
        agents = self._agents()
        stop_all(agents, timeout=10)
        for pr in agents:
            rc = pr.poll()
            if pr.killed_at is None and rc not in (0, None) and not self._crashed(pr):
                self.crashed.append({"process": pr.name, "exit_code": rc, "sim_time_s": self.mon.t, "log_tail": pr.tail()})
        world = self.procs["world"]
        try:
            wrc = world.wait(15)
        except subprocess.TimeoutExpired:
            wrc = world.stop()
        if wrc != 0:
            self.crashed.append({"process": "world", "exit_code": wrc, "sim_time_s": self.mon.t, "log_tail": world.tail()})
        self._stop_recorder()
        self.mon.close()
        self.diags, self.estimates = self.mon.results()

    # --- stop ------------------------------------------------------------------------------------

    def stop(self) -> None:
        """Whatever still runs, in order: agents (SIGTERM, so each commands zero; 5 s), then the world, then our
        session, then the router. Safe after :meth:`serve`, after a failed :meth:`start` and on errors."""
        stop_all(self._agents(), timeout=5)
        for pr in self.procs.values():
            if pr.poll() is None:
                pr.stop(5)
        self._stop_recorder()
        if self.session is not None:
            if self.ack_pub is not None:
                self.ack_pub.undeclare()
                self.ack_pub = None
            if self.mon is not None:
                self.mon.close()
            self.session.close()
            self.session = None
        for pr in [*self.procs.values(), *self.retired]:
            pr.close()
        if self.router is not None:
            self.router.stop(5)
            self.router.close()

    def run(self) -> tuple[int, dict]:
        """Start, serve and stop the fleet; (exit code, report). Ctrl-C (or SIGTERM, see
        :func:`sigterm_as_interrupt`) stops it the same way and propagates."""
        try:
            self.start()
            self.serve()
        except _Abort:
            pass
        finally:
            self.stop()
        report = build_report(self.sc, self.out, diags=self.diags, estimates=self.estimates, faults=self.faults,
                              crashed=self.crashed, wall_time_s=time.monotonic() - self.wall0,
                              realtime=self.cfg.realtime, plots=self.cfg.plots, router_restarts=self.router_restarts)
        self._replay()
        code = EXIT_CRASH if self.crashed else (EXIT_OK if report["success"] else EXIT_FAILED)
        return code, report

    def _replay(self) -> None:
        """``replay.gif`` from the recording (with the plots); a replay that cannot be drawn is a warning."""
        if not (self.cfg.record and self.cfg.plots and (self.out / "run.mcap").exists()):
            return
        from .replay import ReplayError, render_replay

        try:  # two frames per second of the run (at most 150): a short run's replay costs little
            render_replay(self.out, max_frames=max(10, min(150, round(2 * self.mon.t))) if self.mon else 150)
        except ReplayError as e:
            log.warning("no replay: %s", e)


def run_fleet(cfg: FleetConfig) -> tuple[int, dict]:
    """Run one fleet to its end; returns (exit code, report)."""
    return Fleet(cfg).run()

class _Progress:
    """A live progress line: sim time, leader distance to goal, speed."""

    def __init__(self, sc: Scenario, enabled: bool):
        self.enabled = enabled
        self.sc = sc
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=round(sc.duration, 1), unit="sim s", desc=sc.name, file=sys.stderr,
                            mininterval=0.5, leave=True)
            self._last = 0.0

    def update(self, t: float, wall: float) -> None:
        if self.bar is None:
            return
        t = round(min(t, self.sc.duration), 1)
        if t > self._last:
            self.bar.update(t - self._last)
            self._last = t
            self.bar.set_postfix_str(f"x{t / wall:.1f} real time" if wall > 0 else "", refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
