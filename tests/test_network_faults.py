"""The network failing under a real-time fleet: a router restart, a flapping router, one of two routers dying.

Real processes throughout: a ``stack-router`` the test owns (killed with SIGKILL, started again on the same
endpoint), ``stack-fleet run --realtime --connect`` joining it, and the fleet's own agents and world as child
processes. Each run's report must show the mission succeeding, no collision, never two leaders, and each
robot standing still (the world's truth) while nobody could hear it.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import ROOT, scenario_dict, write_scenario

from stack.agents.quorum import Membership, is_quorum
from stack.comm import Keys
from stack.comm.link import GoneJudge, LinkWatch
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session

OUTAGE_S = 3.0
STOP_S = 0.5
"""[s] the wheels' braking from cruise (3 m/s^2 at the default base) and a step of the world noticing the loss."""


class Router:
    """A ``stack-router`` process on a fixed endpoint that the test kills and starts again."""

    def __init__(self, endpoint: str, log: Path, connect: str | None = None):
        self.endpoint, self.log, self.connect, self.proc = endpoint, log, connect, None

    def start(self) -> None:
        argv = [sys.executable, "-m", "stack.comm.router", "--listen", self.endpoint]
        if self.connect:
            argv += ["--connect", self.connect]
        self.proc = subprocess.Popen(argv, cwd=ROOT, stdout=self.log.open("a"), stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 20
        while "listening" not in self.log.read_text():
            assert self.proc.poll() is None and time.monotonic() < deadline, self.log.read_text()
            time.sleep(0.05)

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()
        self.log.write_text(self.log.read_text().replace("listening", "was listening"))

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.kill()


class Proxy:
    """A TCP forwarder on loopback between a router and the router it meshes with: ``cut`` closes every
    connection through it and refuses new ones (a partition: both sides keep their own router), ``mend`` lets
    them through again."""

    def __init__(self, target: str):
        self.target = target.split("/", 1)[1].rsplit(":", 1)
        self.cut_now = threading.Event()
        self._socks: list[socket.socket] = []
        self._lock = threading.Lock()
        self._srv = socket.create_server(("127.0.0.1", 0))
        self.endpoint = f"tcp/127.0.0.1:{self._srv.getsockname()[1]}"
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                c, _ = self._srv.accept()
            except OSError:
                return
            if self.cut_now.is_set():
                c.close()
                continue
            u = socket.create_connection((self.target[0], int(self.target[1])))
            with self._lock:
                self._socks += [c, u]
            for a, b in ((c, u), (u, c)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(a: socket.socket, b: socket.socket) -> None:
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        for x in (a, b):
            try:
                x.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self) -> None:
        self.cut_now.set()
        with self._lock:
            socks, self._socks = self._socks, []
        for x in socks:
            try:
                x.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            x.close()

    def mend(self) -> None:
        self.cut_now.clear()

    def close(self) -> None:
        self.cut()
        self._srv.close()


def fleet(scenario: Path, out: Path, connect: str, *extra: str) -> subprocess.Popen:
    argv = [sys.executable, "-m", "stack.fleet", "run", str(scenario), "--realtime", "--connect", connect,
            "--out", str(out), "--no-progress", "--no-plots", "--fleet", out.name, *extra]
    return subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def wait_first_clock(connect: str, fleet_name: str, timeout: float = 60.0) -> None:
    """Until the world's first real-time clock (the run has begun)."""
    got = threading.Event()
    with open_session(SessionConfig(connect=connect.split(","))) as s:
        s.declare_subscriber(Keys(fleet_name).world("clock"), lambda _s: got.set())
        assert got.wait(timeout), "the world never stepped"


def short_diamond(duration: float = 30.0) -> dict:
    d = scenario_dict(duration=duration)
    d["success"] = dict(d["success"], max_time=duration)
    d["robot"] = dict(d["robot"], cmd_timeout=0.5)
    return d


def finish(proc: subprocess.Popen, out: Path, timeout: float = 150) -> dict:
    text, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, text[-3000:]
    return json.loads((out / "report.json").read_text())


def assert_rode_through(report: dict, out: Path, outage: tuple[float, float] | None, timeout_s: float) -> None:
    """Success, no collision, never two leaders; where ``outage`` (sim times) is given, every robot stood still in
    the world's truth from ``timeout_s`` (its watchdog) and its braking (``STOP_S``) after the outage began until
    it ended."""
    assert report["success"], report
    assert report["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    assert report["network"]["two_leaders_s"] == 0.0, report["network"]
    assert report["end_reason"] == "task complete"
    if outage is None:
        return
    tr = np.load(out / "truth.npz")
    t0, t1 = outage
    during = (tr["t"] >= t0 + timeout_s + STOP_S) & (tr["t"] <= t1)
    assert during.sum() >= 10, (t0, t1)
    assert np.abs(tr["v"][during]).max() < 1e-6 and np.abs(tr["w"][during]).max() < 1e-6


def nobody_left(out: Path) -> bool:
    """No robot called gone during the run (at its end every agent leaves)."""
    w = json.loads((out / "world.json").read_text())
    return not [e for e in w["events"] if e["event"] == "left" and e["t"] < w["sim_time_s"]]


def world_outage(report: dict) -> tuple[float, float]:
    got = [o for o in report["network"]["outages"] if o["cause"].startswith("the world")]
    assert len(got) == 1 and got[0]["end"] is not None, report["network"]
    assert got[0]["robots"] == [0, 1, 2, 3]
    return got[0]["start"], got[0]["end"]


# --- the rules, alone --------------------------------------------------------------------------------------


def test_two_sides_of_a_partition_are_never_both_a_quorum():
    ids = {0, 1, 2, 3}
    for mask in range(1, 15):
        a = {r for r in ids if mask >> r & 1}
        assert is_quorum(a, ids, 0) != is_quorum(ids - a, ids, 0), a
    m = Membership(ids, leader=0)
    assert m.update({0})  # the leader died: three of four go on (failover as before)
    assert m.members == {1, 2, 3}
    assert m.update({0, 3})  # then a follower: two of three
    assert not m.update({0, 1, 3})  # the last one of a pair that lost the first in the failover order holds
    assert m.update(set())  # everyone back: the whole fleet again
    assert m.members == ids


def test_a_token_lost_with_our_own_link_is_not_a_peer_gone(tmp_path: Path):
    """A real router killed under two clients: the peer's token goes away with the link, and is not judged gone;
    back within the rejoin time, nobody is gone; a peer that leaves while the link is up is gone."""
    ep = free_tcp_endpoint()
    router = Router(ep, tmp_path / "router.log")
    router.start()
    try:
        with open_session(SessionConfig(connect=[ep])) as a, open_session(SessionConfig(connect=[ep])) as b:
            watch = LinkWatch(b)
            judge = GoneJudge(watch, confirm_s=0.3, rejoin_s=1.5)

            def on_alive(sample):
                rid = int(str(sample.key_expr).rsplit("/", 1)[-1])
                (judge.deleted if sample.kind == zenoh.SampleKind.DELETE else judge.returned)(rid)

            b.liveliness().declare_subscriber("t/alive/*", on_alive, history=True)
            token = a.liveliness().declare_token("t/alive/7")
            gone: list[int] = []

            def tick(seconds: float) -> None:
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    watch.poll()
                    gone.extend(judge.confirmed())
                    time.sleep(0.05)

            tick(0.5)
            assert judge.present == {7} and watch.up
            router.kill()
            tick(1.0)
            assert not watch.up and watch.lost_since is not None and gone == []
            router.start()
            tick(4.0)
            assert watch.up and judge.present == {7} and gone == [], (gone, judge.present)
            assert len(watch.outages) == 1 and watch.outages[0].end is not None
            assert judge.discarded == 1
            token.undeclare()
            tick(1.0)
            assert gone == [7]
    finally:
        router.close()


# --- fleets ------------------------------------------------------------------------------------------------


@pytest.mark.fleet
@pytest.mark.parametrize("driver", ["sim", "can"])
def test_router_restart_in_a_real_time_run(tmp_path: Path, driver: str):
    """The issue's case: the fleet's router killed 5 s into a real-time diamond and started 3 s later; on the
    world's base (its watchdog stops the bodies: the commands cannot reach it) and on hardware-like CAN devices
    (the agents' own hold: their commands reach the devices over CAN, not Zenoh)."""
    ep = free_tcp_endpoint()
    d = short_diamond()
    sc = write_scenario(tmp_path / "diamond.yaml", d)
    router = Router(ep, tmp_path / "router.log")
    router.start()
    out = tmp_path / "rr"
    try:
        proc = fleet(sc, out, ep, "--driver", driver)
        wait_first_clock(ep, out.name)
        time.sleep(5.0)
        router.kill()
        time.sleep(OUTAGE_S)
        router.start()
        report = finish(proc, out)
    finally:
        router.close()
    t0, t1 = world_outage(report)
    assert OUTAGE_S - 0.5 < t1 - t0 < OUTAGE_S + 2.0
    assert_rode_through(report, out, (t0, t1), d["robot"]["cmd_timeout"])
    net = report["network"]
    assert sorted(net["agent_outages"]) == ["0", "1", "2", "3"], net
    assert list(net["led"]) == ["0"], net  # nobody else ever led
    assert report["faults"] == [] and report["crashed"] == []


def agent(scenario: Path, rid: int, connect: str, fleet_name: str, log: Path) -> subprocess.Popen:
    argv = [sys.executable, "-m", "stack.agents", "--id", str(rid), "--scenario", str(scenario), "--connect", connect,
            "--fleet", fleet_name, "--log-level", "INFO"]
    return subprocess.Popen(argv, cwd=ROOT, stdout=log.open("w"), stderr=subprocess.STDOUT)


@pytest.mark.fleet
def test_a_partition_leaves_one_leader_driving(tmp_path: Path):
    """Two site routers meshed through a link the test cuts for 5 s: the world and robots 0, 1 on one side, robots
    2, 3 on the other, each side still on its own router. Side {2, 3} sees the leader gone and makes robot 2 its
    leader, but two of four without the first in the failover order are no quorum: it holds. The world has 2 and
    3 out of contact, not gone; they rejoin and the mission succeeds."""
    d = short_diamond()
    sc = write_scenario(tmp_path / "diamond.yaml", d)
    ep1, ep2 = free_tcp_endpoint(), free_tcp_endpoint()
    r1 = Router(ep1, tmp_path / "r1.log")
    r1.start()
    link = Proxy(ep1)
    r2 = Router(ep2, tmp_path / "r2.log", connect=link.endpoint)
    r2.start()
    out = tmp_path / "part"
    agents = [agent(sc, rid, ep1 if rid < 2 else ep2, out.name, tmp_path / f"agent-{rid}.log") for rid in range(4)]
    try:
        proc = fleet(sc, out, ep1, "--external-agents")
        wait_first_clock(ep1, out.name)
        time.sleep(4.0)
        link.cut()
        time.sleep(5.0)
        link.mend()
        report = finish(proc, out)
    finally:
        for p in agents:
            p.terminate()
        for p in agents:
            p.wait(timeout=30)
        link.close()
        r2.close()
        r1.close()
    logs = {rid: (tmp_path / f"agent-{rid}.log").read_text() for rid in range(4)}
    assert "agent 2: now leader" in logs[2], logs[2][-2000:]
    net = report["network"]
    assert_rode_through(report, out, None, d["robot"]["cmd_timeout"])
    assert list(net["led"]) == ["0"], net  # robot 2 took the role but never drove as leader
    assert net["held_steps"].get("2", 0) >= 30, net
    out_of_contact = {o["robots"][0]: o for o in net["outages"] if o["cause"] == "robot out of contact"}
    assert sorted(out_of_contact) == [2, 3] and all(o["end"] is not None for o in out_of_contact.values()), net
    assert all(4.0 <= o["end"] - o["start"] <= 7.0 for o in out_of_contact.values()), net
    assert nobody_left(out)


@pytest.mark.fleet
def test_a_flapping_router_and_one_of_two_routers_dying(tmp_path: Path):
    """Every client lists two meshed routers. The first is killed for good 4 s in (everyone moves to the second,
    costing no more than the reconnect); then the second flaps, down and up every second for 10 s, and stays up.
    No crash, no leader but the scenario's, the run ends normally."""
    d = short_diamond(duration=45.0)
    sc = write_scenario(tmp_path / "diamond.yaml", d)
    ep1, ep2 = free_tcp_endpoint(), free_tcp_endpoint()
    r1, r2 = Router(ep1, tmp_path / "r1.log"), Router(ep2, tmp_path / "r2.log", connect=ep1)
    r1.start()
    r2.start()
    out = tmp_path / "flap"
    try:
        proc = fleet(sc, out, f"{ep1},{ep2}")
        wait_first_clock(ep1, out.name)
        time.sleep(4.0)
        r1.kill()
        time.sleep(3.0)
        for _ in range(5):
            r2.kill()
            time.sleep(1.0)
            r2.start()
            time.sleep(1.0)
        report = finish(proc, out)
    finally:
        r2.close()
        r1.close()
    assert_rode_through(report, out, None, d["robot"]["cmd_timeout"])
    net = report["network"]
    assert list(net["led"]) == ["0"], net
    assert nobody_left(out)
