"""The Fleet's lifecycle in process: shutdown order, crash detection, faults, a start that fails.

Fake processes where only the bookkeeping matters; tiny real processes (and a real router) where
signals and exits must really happen.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import scenario_dict

from stack.comm.messages import FaultRequest
from stack.fleet.orchestrator import EXIT_CRASH, Fleet, FleetConfig, run_fleet
from stack.fleet.procs import Proc, stop_all
from stack.scenario import parse_scenario


class FakeProc(Proc):
    """A process that ends when signalled (SIGTERM, SIGKILL) and writes every signal into a shared journal
    (Proc's own kill and stop on top)."""

    def __init__(self, name: str, journal: list, rc: int | None = None, ignores_term: bool = False):
        self.name, self.journal, self.rc, self.ignores_term = name, journal, rc, ignores_term
        self.asked_to_stop, self.killed_at, self.frozen, self.exited_at, self.closed = False, None, False, None, False

    def poll(self):
        return self.rc

    def wait(self, timeout):
        if self.rc is None:
            raise subprocess.TimeoutExpired(self.name, timeout)
        return self.rc

    def signal(self, sig):
        if self.rc is None:
            self.journal.append((self.name, signal.Signals(sig).name))
            if sig == signal.SIGKILL or (sig == signal.SIGTERM and not self.ignores_term):
                self.rc = -9 if sig == signal.SIGKILL else 0

    def tail(self, n=5):
        return f"{self.name} log"

    def close(self):
        self.closed = True


def config(tmp_path: Path, **kw) -> FleetConfig:
    return FleetConfig(scenario=parse_scenario(scenario_dict()), out=tmp_path, progress=False, plots=False,
                       listen="tcp/127.0.0.1:1", **kw)


def fake_fleet(tmp_path: Path, journal: list, **kw) -> Fleet:
    fleet = Fleet(config(tmp_path, **kw), spawn=lambda name, argv, log, env: FakeProc(name, journal))
    fleet.router = FakeProc("router", journal)
    fleet.procs = {"world": FakeProc("world", journal)} | {f"agent-{i}": FakeProc(f"agent {i}", journal) for i in range(4)}
    return fleet


def test_stop_ends_the_agents_first_then_the_world_then_the_router(tmp_path):
    journal: list = []
    fleet = fake_fleet(tmp_path, journal)
    fleet.procs["agent-2"].frozen = True
    fleet.procs["agent-3"].ignores_term = True  # a straggler: SIGKILL, still before the world is asked
    fleet.stop()
    names = [n for n, _ in journal]
    assert journal[:2] == [("agent 0", "SIGTERM"), ("agent 1", "SIGTERM")]
    assert ("agent 2", "SIGCONT") in journal and journal.index(("agent 2", "SIGCONT")) < journal.index(("agent 2", "SIGTERM"))
    assert journal.index(("agent 3", "SIGKILL")) < names.index("world") < names.index("router")
    assert journal[-2:] == [("world", "SIGTERM"), ("router", "SIGTERM")]
    assert all(p.closed for p in fleet.procs.values()) and fleet.router.closed


def test_crash_detection(tmp_path):
    fleet = fake_fleet(tmp_path, [])
    p = fleet.procs
    p["agent-0"].rc = 1  # crashed
    p["agent-1"].rc = 0  # ended by itself just now: give the world's "done" 2 s to arrive
    p["agent-2"].rc, p["agent-2"].killed_at = -9, 3.0  # our --kill
    p["world"].rc = 1  # the world's own exit is judged at the end, not here
    fleet.note_crashes(4.2, "running")
    assert fleet.crashed == [{"process": "agent 0", "exit_code": 1, "sim_time_s": 4.2, "log_tail": "agent 0 log"}]
    assert fleet.faults == [{"robot": 0, "kind": "crashed", "exit_code": 1, "sim_time_s": 4.2}]
    fleet.note_crashes(4.3, "running")
    assert len(fleet.crashed) == 1  # once per process
    p["agent-1"].exited_at -= 2.5
    fleet.note_crashes(4.4, "running")
    assert [c["process"] for c in fleet.crashed] == ["agent 0", "agent 1"]
    p["agent-3"].rc = 2
    fleet.note_crashes(4.5, "done")  # once the world is done, agents end: no crash
    assert len(fleet.crashed) == 2


def test_faults_the_world_asks_for(tmp_path):
    journal: list = []
    fleet = fake_fleet(tmp_path, journal, faults=[("kill", 1, 2.0), ("freeze", 2, 3.0), ("restart", 2, 6.0)])
    old = fleet.procs["agent-2"]
    assert fleet.do_fault(FaultRequest(kind="kill", ids=[1], t=2.0, step=20), 1)
    assert not fleet.do_fault(FaultRequest(kind="kill", ids=[3], t=2.0, step=20), 3)  # not asked for on our command line
    assert fleet.do_fault(FaultRequest(kind="freeze", ids=[2], t=3.0, step=30), 2)
    assert fleet.do_fault(FaultRequest(kind="restart", ids=[2], t=6.1, step=61), 2)
    assert journal == [("agent 1", "SIGKILL"), ("agent 2", "SIGSTOP"), ("agent 2", "SIGCONT"), ("agent 2", "SIGKILL")]
    assert fleet.procs["agent-1"].killed_at == 2.0 and old.killed_at == 6.1
    assert fleet.retired == [old] and fleet.procs["agent-2"] is not old and fleet.procs["agent-2"].rc is None
    assert [(f["robot"], f["kind"], f["at_s"], f["sim_time_s"]) for f in fleet.faults] == \
        [(1, "killed", 2.0, 2.0), (2, "frozen", 3.0, 3.0), (2, "restarted", 6.0, 6.1)]
    fleet.note_crashes(7.0, "running")
    assert fleet.crashed == []  # the killed and the replaced agents did not crash


def test_a_router_that_does_not_start_is_a_crash_with_a_report(tmp_path):
    started = []

    def spawn(name, argv, log, env):
        started.append(name)
        return FakeProc(name, [], rc=1)  # exits at once

    code, rep = Fleet(config(tmp_path), spawn=spawn).run()
    assert code == EXIT_CRASH and started == ["router"]
    assert rep["crashed"][0]["process"] == "router" and "exited with code 1" in rep["crashed"][0]["log_tail"]
    assert rep["end_reason"] == "no world log" and (tmp_path / "report.json").exists()
    assert (tmp_path / "scenario.resolved.yaml").exists()


# --- tiny real processes -------------------------------------------------------------------------

CHILD = """
import pathlib, signal, sys, time
journal, name, mode = sys.argv[1:4]
ready = pathlib.Path(journal).parent / "ready"
def on_term(*_):
    with open(journal, "a") as f:
        f.write(f"{name} {time.monotonic()}\\n")
    sys.exit(0)
signal.signal(signal.SIGTERM, on_term)
ready.mkdir(exist_ok=True)
(ready / name).touch()
if mode == "crash":
    sys.exit(1)
if mode.startswith("end-after-"):  # the world: ends (code 0) once that many others are up
    while len(list(ready.iterdir())) < 1 + int(mode.split("-")[-1]):
        time.sleep(0.02)
    time.sleep(0.3)
    sys.exit(0)
time.sleep(60)
"""
"""A stand-in for the world or an agent: records SIGTERM (then exits 0) in the journal, touches ready/NAME
once its handler is in place; ``wait``: until SIGTERM, ``crash``: exit 1 then, ``end-after-N``: exit 0
once N others are ready."""


def wait_ready(tmp_path: Path, n: int) -> None:
    deadline = time.monotonic() + 30
    while not ((tmp_path / "ready").is_dir() and len(list((tmp_path / "ready").iterdir())) >= n):
        assert time.monotonic() < deadline, "the stand-in processes did not start"
        time.sleep(0.02)


class Recorded(Proc):
    """A real process; every SIGTERM we send it goes into ``sent`` with the time."""

    sent: list = []

    def signal(self, sig):
        if sig == signal.SIGTERM and self.poll() is None:
            Recorded.sent.append((self.name, time.monotonic()))
        super().signal(sig)


def real_spawn(tmp_path: Path, world: str, agent1: str):
    """The real router; world and agents replaced by CHILD."""
    def spawn(name, argv, log, env):
        if name == "router":
            return Recorded(name, argv, log, env)
        mode = world if name == "world" else agent1 if name == "agent 1" else "wait"
        return Recorded(name, [sys.executable, "-c", CHILD, str(tmp_path / "term.log"), name, mode], log, env)
    return spawn


def terms(tmp_path: Path) -> dict[str, float]:
    lines = (tmp_path / "term.log").read_text().split("\n")
    return {" ".join(ln.split()[:-1]): float(ln.split()[-1]) for ln in lines if ln}


def test_a_real_agent_crash_and_the_ordered_wind_down(tmp_path):
    Recorded.sent = []
    fleet = Fleet(config(tmp_path / "out", wall_timeout_s=60), spawn=real_spawn(tmp_path, world="end-after-4", agent1="crash"))
    fleet.endpoint = _free_endpoint()
    code, rep = fleet.run()
    assert code == EXIT_CRASH
    assert [(c["process"], c["exit_code"]) for c in rep["crashed"]] == [("agent 1", 1)]
    assert [(f["robot"], f["kind"]) for f in rep["faults"]] == [(1, "crashed")]
    got = terms(tmp_path)
    assert set(got) == {"agent 0", "agent 2", "agent 3"}  # each live agent got SIGTERM and left with code 0
    sent = dict(Recorded.sent)
    assert max(sent[f"agent {i}"] for i in (0, 2, 3)) < sent["router"]
    assert "world" not in sent  # it ended by itself (code 0): no crash
    assert all(p.poll() is not None for p in [*fleet.procs.values(), fleet.router])


def test_ctrl_c_stops_agents_then_world_then_router(tmp_path, monkeypatch):
    Recorded.sent = []
    fleet = Fleet(config(tmp_path / "out"), spawn=real_spawn(tmp_path, world="wait", agent1="wait"))
    fleet.endpoint = _free_endpoint()
    ticks = []
    real_tick = fleet.tick

    def tick(progress=None):
        wait_ready(tmp_path, 5)  # the world and every agent are up, their handlers in place
        ticks.append(1)
        if len(ticks) == 5:
            raise KeyboardInterrupt
        return real_tick(progress)

    monkeypatch.setattr(fleet, "tick", tick)
    with pytest.raises(KeyboardInterrupt):
        fleet.run()
    got = terms(tmp_path)
    assert set(got) == {"agent 0", "agent 1", "agent 2", "agent 3", "world"}
    assert max(got[f"agent {i}"] for i in range(4)) < got["world"]  # the agents had left before the world was asked
    sent = dict(Recorded.sent)
    assert sent["world"] < sent["router"]
    assert all(p.poll() is not None for p in [*fleet.procs.values(), fleet.router])


def _state(pid: int) -> str:
    """A process's state letter (/proc/PID/stat: R, S, T for stopped, ...)."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_stop_all_real_processes(tmp_path):
    journal = tmp_path / "term.log"
    procs = [Proc(f"p{i}", [sys.executable, "-c", CHILD, str(journal), f"p{i}", "wait"], tmp_path / f"p{i}.log", {})
             for i in range(2)]
    stubborn = Proc("stubborn", [sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                                 "open(__import__('sys').argv[1], 'w').close(); time.sleep(60)", str(tmp_path / "up")],
                    tmp_path / "s.log", {})
    wait_ready(tmp_path, 2)
    while not (tmp_path / "up").exists():
        time.sleep(0.02)
    procs[1].frozen = True
    procs[1].signal(signal.SIGSTOP)
    stopped = time.monotonic() + 5.0  # frozen for real before stop_all lets it go (a fresh-clone CI run once saw
    while _state(procs[1].p.pid) != "T" and time.monotonic() < stopped:  # it SIGKILLed instead: a stop still in
        time.sleep(0.01)  # flight when the SIGCONT and SIGTERM came)
    assert _state(procs[1].p.pid) == "T"
    stop_all(procs, timeout=15.0)  # generous: a let-go process under a loaded CI took over 5 s to run its handler
    assert [p.poll() for p in procs] == [0, 0]  # the frozen one was let go and handled its SIGTERM
    t = time.monotonic()
    stop_all([stubborn], timeout=1.0)  # one that ignores SIGTERM is SIGKILLed at the deadline
    assert stubborn.poll() == -signal.SIGKILL and time.monotonic() - t < 5.0
    assert set(terms(tmp_path)) == {"p0", "p1"}
    for p in [*procs, stubborn]:
        p.close()


def _free_endpoint() -> str:
    from stack.comm.session import free_tcp_endpoint

    return free_tcp_endpoint()


def test_run_fleet_is_a_thin_wrapper(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(Fleet, "run", lambda self: seen.append(self.cfg) or (0, {}))
    cfg = config(tmp_path)
    assert run_fleet(cfg) == (0, {}) and seen == [cfg]
