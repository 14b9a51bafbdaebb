"""``stack-fleet run``: a Zenoh router on loopback, the world, one ``stack-agent`` process per robot.

The orchestrator watches the run over Zenoh (world clock and status, agents' diag and
state), injects ``--kill ID@T`` faults, notices crashes, stops everything in order
(agents first: SIGTERM -> their zero commands; then the world; then the router) and
writes ``report.json`` and the plots.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from ..comm import Keys, receive
from ..comm import encode
from ..comm.messages import Clock, Diag, FaultAck, FaultRequest, State, WorldStatus
from ..comm.session import SessionConfig, SessionError, free_tcp_endpoint, open_session
from ..scenario import Scenario, with_driver_settings
from .report import build_report

log = logging.getLogger("stack.fleet")

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_CRASH = 0, 1, 2, 3
ZENOH_RUNTIME = "(app: (worker_threads: 1), tx: (handover: app), rx: (handover: app), acc: (handover: app), net: (handover: app))"


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
    zenoh_config: str | None = None
    """A zenoh json5 file (deploy/: TLS, access control) for our own session and the world's."""
    allow_remote: bool = False
    """Allow router endpoints off loopback (multi-host)."""


RUN_OUTPUTS = ("report.json", "truth.npz", "world.json", "devices.json", "scenario.agents.yaml", "trajectories.png",
               "distances.png", "errors.png")
"""What a run writes into its folder (besides ``logs/`` and the resolved scenario)."""


def sigterm_as_interrupt() -> None:
    """SIGTERM tears a fleet down in order (agents' zero commands first), exactly like Ctrl-C."""
    def on_term(signum, _frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)


class _Proc:
    def __init__(self, name: str, argv: list[str], log_path: Path, env: dict):
        self.name = name
        self.log_path = log_path
        self.log_file = open(log_path, "wb")
        self.p = subprocess.Popen(argv, stdout=self.log_file, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        self.asked_to_stop = False
        self.killed_at: float | None = None
        self.frozen = False
        self.exited_at: float | None = None

    def poll(self) -> int | None:
        return self.p.poll()

    def signal(self, sig: int) -> None:
        if self.p.poll() is None:
            try:
                self.p.send_signal(sig)
            except ProcessLookupError:
                pass

    def stop(self, timeout: float = 5.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout``."""
        self.asked_to_stop = True
        self.signal(signal.SIGTERM)
        try:
            return self.p.wait(timeout)
        except subprocess.TimeoutExpired:
            self.signal(signal.SIGKILL)
            return self.p.wait(5)

    def tail(self, n: int = 5) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(lines[-n:])

    def close(self) -> None:
        self.log_file.close()


def _stop_all(procs: list[_Proc], timeout: float) -> None:
    """SIGTERM every running process at once (agents: zero velocity on the way out), then wait; SIGKILL stragglers.
    A frozen (SIGSTOPped) agent is let go on first, so it can command its zero too."""
    running = [pr for pr in procs if pr.poll() is None]
    for pr in running:
        pr.asked_to_stop = True
        if pr.frozen:
            pr.signal(signal.SIGCONT)
            pr.frozen = False
        pr.signal(signal.SIGTERM)
    for pr in running:
        try:
            pr.p.wait(timeout)
        except subprocess.TimeoutExpired:
            pr.signal(signal.SIGKILL)
            pr.p.wait(5)


def _agents_scenario(sc: Scenario, out: Path, world: _Proc, timeout: float = 30.0, can_log: bool = False) -> Path:
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
    settings = {int(rid): dict(d["settings"]) for rid, d in devices.items()}
    if can_log:
        for r in sc.robots:
            if r.driver == "can":
                settings[r.id]["can_log"] = str(out / "logs" / f"can-{r.id}.asc")
    agents = with_driver_settings(sc, settings)
    target = out / "scenario.agents.yaml"
    target.write_text(agents.to_yaml())
    return target


class _Abort(Exception):
    """The fleet could not start; the report says why."""


def _wait_port(endpoint: str, timeout: float = 10.0, process: "_Proc | None" = None) -> None:
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process is not None and process.poll() is not None:
            raise TimeoutError(f"router exited with code {process.poll()} before opening {endpoint}")
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"router did not open {endpoint} within {timeout:.0f} s")


class Monitor:
    """What the orchestrator hears on Zenoh during a run."""

    def __init__(self, session: zenoh.Session, keys: Keys):
        self.lock = threading.Lock()
        self.t = 0.0
        self.step = 0
        self.status = "starting"
        self.why = ""
        self.diag: dict[int, Diag] = {}
        self.estimates: dict[int, list[tuple[int, float, float]]] = {}
        self.situation: dict[int, str] = {}
        self.alive: set[int] = set()
        self.malformed = 0
        self.fault_requests: list[FaultRequest] = []
        self._subs = [
            session.declare_subscriber(keys.world("fault"), self._on(FaultRequest, self.fault_requests.append)),
            session.declare_subscriber(keys.world("clock"), self._on(Clock, self._clock)),
            session.declare_subscriber(keys.world("status"), self._on(WorldStatus, self._status)),
            session.declare_subscriber(keys.all_robots("diag"), self._on(Diag, self._diag)),
            session.declare_subscriber(keys.all_robots("state"), self._on(State, self._state)),
            session.liveliness().declare_subscriber(keys.all_alive, self._alive, history=True),
        ]

    def _alive(self, sample: zenoh.Sample) -> None:
        rid = Keys.id_of(str(sample.key_expr))
        if rid is None:
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self.alive.discard(rid)
            else:
                self.alive.add(rid)

    def wait_alive(self, ids: set[int], timeout: float) -> set[int]:
        """Wait until every id has a liveliness token; returns the ones still missing."""
        deadline = time.monotonic() + timeout
        while True:
            with self.lock:
                missing = ids - self.alive
            if not missing or time.monotonic() > deadline:
                return missing
            time.sleep(0.1)

    def _on(self, kind, handler):
        def callback(sample: zenoh.Sample) -> None:
            m = receive(sample, kind, self._bad)
            if m is not None:
                with self.lock:
                    handler(m)
        return callback

    def _bad(self, _key: str) -> None:
        with self.lock:
            self.malformed += 1

    def _clock(self, m: Clock) -> None:
        self.t, self.step = m.t, m.step

    def _status(self, m: WorldStatus) -> None:
        self.status, self.why = m.state, m.why

    def _diag(self, m: Diag) -> None:
        old = self.diag.get(m.id)
        if old is None or m.step >= old.step or m.state == "stopped":
            self.diag[m.id] = m

    def _state(self, m: State) -> None:
        self.estimates.setdefault(m.id, []).append((m.step, m.x, m.y))
        if m.situation:
            self.situation[m.id] = m.situation

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def run_fleet(cfg: FleetConfig) -> tuple[int, dict]:
    """Run one fleet to its end; returns (exit code, report)."""
    sc = cfg.scenario
    out = cfg.out
    (out / "logs").mkdir(parents=True, exist_ok=True)
    for name in RUN_OUTPUTS:  # a folder used before: nothing of that run may pass for this one's
        (out / name).unlink(missing_ok=True)
    resolved = out / "scenario.resolved.yaml"
    resolved.write_text(sc.to_yaml())
    fleet = cfg.fleet or f"run{os.getpid()}"
    keys = Keys(fleet)
    endpoint = cfg.connect or cfg.listen or free_tcp_endpoint()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # many small processes on few cores: one zenoh worker thread each (fleet_bench: +15 % steps/s at 32 robots)
    env.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
    py = sys.executable
    procs: dict[str, _Proc] = {}
    faults: list[dict] = []
    crashed: list[dict] = []
    wall0 = time.monotonic()
    wall_limit = cfg.wall_timeout_s or max(120.0, sc.duration * (3.0 if cfg.realtime else 2.0) + 60.0)

    remote = ["--allow-remote"] if cfg.allow_remote else []
    zconf = ["--zenoh-config", cfg.zenoh_config] if cfg.zenoh_config else []
    router = None
    if cfg.connect is None:
        router = _Proc("router", [py, "-m", "stack.comm.router", "--listen", endpoint, *remote]
                       + (["--config", cfg.zenoh_config] if cfg.zenoh_config else []), out / "logs" / "router.log", env)
    try:
        if router is not None:
            try:
                _wait_port(endpoint, process=router)
            except TimeoutError as e:
                crashed.append({"process": "router", "exit_code": router.poll(), "sim_time_s": 0.0,
                                "log_tail": f"{e}: {router.tail(2)}"})
                raise _Abort from None
        session_cfg = SessionConfig(mode="client", connect=[endpoint], config_file=cfg.zenoh_config,
                                    allow_remote=cfg.allow_remote)
        try:
            session = open_session(session_cfg)
        except SessionError as e:
            crashed.append({"process": "orchestrator", "exit_code": None, "sim_time_s": 0.0, "log_tail": str(e)})
            raise _Abort from None
        with session:
            mon = Monitor(session, keys)
            world_argv = [py, "-m", "stack.sim_bridge", "--scenario", str(resolved), "--connect", endpoint, "--fleet", fleet,
                          "--out", str(out), "--wait-agents", f"{cfg.wait_agents_s:g}", *remote, *zconf]
            if cfg.realtime:
                world_argv.append("--realtime")
            if cfg.gui:
                world_argv.append("--gui")
            for kind, rid, at in cfg.faults:
                world_argv += ["--" + kind, f"{rid}@{at:g}"]
            for rid, at in cfg.device_faults:
                world_argv += ["--device-fault", f"{rid}@{at:g}"]
            procs["world"] = _Proc("world", world_argv, out / "logs" / "world.log", env)
            agents_scenario = resolved
            if any(r.driver != "sim" for r in sc.robots) and not cfg.external_agents:
                # robots on simulated hardware: their drivers go where the world put each device
                try:
                    agents_scenario = _agents_scenario(sc, out, procs["world"], can_log=cfg.can_log)
                except TimeoutError as e:
                    crashed.append({"process": "world", "exit_code": procs["world"].poll(), "sim_time_s": 0.0,
                                    "log_tail": f"{e}: {procs['world'].tail(3)}"})
                    raise _Abort from None

            def start_agent(r, log_name: str) -> _Proc:
                argv = [py, "-m", "stack.agents", "--id", str(r.id), "--scenario", str(agents_scenario), "--connect", endpoint,
                        "--fleet", fleet, "--log-level", "INFO", *remote, *zconf]
                if r.role:
                    argv += ["--role", r.role]
                if not cfg.realtime:
                    argv.append("--lockstep")
                return _Proc(f"agent {r.id}", argv, out / "logs" / log_name, env)

            if cfg.external_agents:
                missing = mon.wait_alive(set(sc.ids), cfg.wait_agents_s)
                if missing:
                    crashed.append({"process": "agents", "exit_code": None, "sim_time_s": 0.0,
                                    "log_tail": f"robots {sorted(missing)} never came up on {endpoint} (fleet "
                                                f"{fleet!r}) within {cfg.wait_agents_s:g} s"})
                    raise _Abort
            else:
                for r in sc.robots:
                    procs[f"agent-{r.id}"] = start_agent(r, f"agent-{r.id}.log")
            ack_pub = session.declare_publisher(keys.world("fault_ack"), congestion_control=zenoh.CongestionControl.BLOCK)
            wanted = {(kind, rid): at for kind, rid, at in cfg.faults}
            retired: list[_Proc] = []  # agents replaced by a restart
            progress = _Progress(sc, enabled=cfg.progress)
            while True:
                time.sleep(0.05)
                with mon.lock:
                    t, status = mon.t, mon.status
                    requests, mon.fault_requests[:] = list(mon.fault_requests), []
                progress.update(t, time.monotonic() - wall0)
                for req in requests:  # the world asks, we do, we answer (it waits for the answer)
                    done = []
                    for rid in req.ids:
                        name = f"agent-{rid}"
                        if name not in procs or (req.kind, rid) not in wanted:
                            continue
                        pr = procs[name]
                        if req.kind == "kill":
                            pr.killed_at = req.t
                            pr.signal(signal.SIGKILL)
                            pr.p.wait(5)
                        elif req.kind == "freeze":
                            pr.frozen = True
                            pr.signal(signal.SIGSTOP)
                        elif req.kind == "restart":
                            if pr.poll() is None:  # still running (e.g. frozen): that one goes first
                                pr.killed_at = req.t
                                if pr.frozen:
                                    pr.signal(signal.SIGCONT)
                                pr.signal(signal.SIGKILL)
                                pr.p.wait(5)
                            retired.append(pr)
                            n = sum(1 for x in retired if x.name == pr.name)
                            procs[name] = start_agent(sc.robot(rid), f"agent-{rid}.restart{n}.log")
                        else:
                            continue
                        done.append(rid)
                        faults.append({"robot": rid, "kind": {"kill": "killed", "freeze": "frozen", "restart": "restarted"}[req.kind],
                                       "at_s": wanted[(req.kind, rid)], "sim_time_s": req.t, "step": req.step})
                    ack_pub.put(encode(FaultAck(step=req.step, kind=req.kind, done=done)))
                for name, pr in procs.items():
                    rc = pr.poll()
                    if rc == 0 and status != "done":
                        # a lock-step agent ends by itself once the world is done; give that news a moment here
                        pr.exited_at = pr.exited_at or time.monotonic()
                        if time.monotonic() - pr.exited_at < 2.0:
                            continue
                    if rc is not None and not pr.asked_to_stop and pr.killed_at is None and name != "world" \
                            and status != "done" and not any(c["process"] == pr.name for c in crashed):
                        crashed.append({"process": pr.name, "exit_code": rc, "sim_time_s": t, "log_tail": pr.tail()})
                        faults.append({"robot": int(name.split("-")[1]), "kind": "crashed", "exit_code": rc, "sim_time_s": t})
                wrc = procs["world"].poll()
                if status == "done" or wrc is not None:
                    break
                if time.monotonic() - wall0 > wall_limit:
                    crashed.append({"process": "world", "exit_code": None, "sim_time_s": t,
                                    "log_tail": f"no end after {wall_limit:.0f} s wall time"})
                    break
            progress.close()
            # stop in order: agents (zero velocity on the way out), then the world, then the router
            agents = [pr for n, pr in procs.items() if n.startswith("agent-")]
            _stop_all(agents, timeout=10)
            for pr in retired:
                pr.close()
            ack_pub.undeclare()
            for pr in agents:
                rc = pr.poll()
                if pr.killed_at is None and rc not in (0, None) and not any(c["process"] == pr.name for c in crashed):
                    crashed.append({"process": pr.name, "exit_code": rc, "sim_time_s": mon.t, "log_tail": pr.tail()})
            world = procs["world"]
            try:
                wrc = world.p.wait(15)
            except subprocess.TimeoutExpired:
                wrc = world.stop()
            if wrc != 0:
                crashed.append({"process": "world", "exit_code": wrc, "sim_time_s": mon.t, "log_tail": world.tail()})
            mon.close()
            with mon.lock:
                diags = dict(mon.diag)
                estimates = {k: list(v) for k, v in mon.estimates.items()}
    except _Abort:
        diags, estimates = {}, {}
    finally:
        # agents first (their zero commands reach the world), then the world
        _stop_all([pr for n, pr in procs.items() if n.startswith("agent-")], timeout=5)
        for pr in procs.values():
            if pr.poll() is None:
                pr.stop(5)
            pr.close()
        if router is not None:
            router.stop(5)
            router.close()

    wall = time.monotonic() - wall0
    report = build_report(sc, out, diags=diags, estimates=estimates, faults=faults, crashed=crashed,
                          wall_time_s=wall, realtime=cfg.realtime, plots=cfg.plots)
    code = EXIT_CRASH if crashed else (EXIT_OK if report["success"] else EXIT_FAILED)
    return code, report


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
