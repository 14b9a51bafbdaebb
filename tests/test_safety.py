"""Every way an agent ends commands zero first: SIGTERM, SIGINT, --steps. Real processes, real Zenoh."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from conftest import ROOT, scenario_dict, wait_port, write_scenario
from stack.comm import Keys, decode
from stack.comm.messages import Clock, CmdVel
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session

pytestmark = pytest.mark.fleet  # router + world + four agent processes


def _spawn(*args: str, log) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", *args], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))


@pytest.mark.parametrize("how", ["SIGTERM", "SIGINT", "steps"])
def test_agent_end_commands_zero(tmp_path, how):
    sc = scenario_dict(duration=8.0)
    path = write_scenario(tmp_path / "s.yaml", sc)
    ep = free_tcp_endpoint()
    fleet = "safety"
    log = open(tmp_path / "log.txt", "wb")
    procs = [_spawn("stack.comm.router", "--listen", ep, log=log)]
    try:
        wait_port(ep)
        cmds: list[CmdVel] = []
        clock = {"t": 0.0}
        lock = threading.Lock()

        def on_cmd(s):
            m = decode(s.payload.to_bytes(), CmdVel)
            with lock:
                cmds.append(m)

        def on_clock(s):
            clock["t"] = decode(s.payload.to_bytes(), Clock).t

        with open_session(SessionConfig(connect=[ep])) as session:
            k = Keys(fleet)
            subs = [session.declare_subscriber(k.robot(0, "cmd_vel"), on_cmd), session.declare_subscriber(k.world("clock"), on_clock)]
            procs.append(_spawn("stack.sim_bridge", "--scenario", str(path), "--connect", ep, "--fleet", fleet, "--out",
                                str(tmp_path / "out"), "--no-stop-early", "--lockstep-timeout", "5", log=log))
            extra = ["--steps", "30"] if how == "steps" else []
            agents = {rid: _spawn("stack.agents", "--id", str(rid), "--scenario", str(path), "--connect", ep, "--fleet", fleet,
                                  "--lockstep", *extra, log=log) for rid in (0, 1, 2, 3)}
            try:
                if how != "steps":
                    deadline = time.monotonic() + 30
                    while clock["t"] < 2.0 and time.monotonic() < deadline:
                        time.sleep(0.01)
                    assert clock["t"] >= 2.0, (tmp_path / "log.txt").read_text()
                    agents[0].send_signal(getattr(signal, how))
                assert agents[0].wait(20) == 0
                time.sleep(0.5)
                with lock:
                    moving = [c for c in cmds if c.step >= 0 and c.v > 0.1]
                    last = cmds[-1]
                assert moving, "the leader never moved"
                assert (last.v, last.w) == (0.0, 0.0), last
                assert last.step == -1  # the stop, outside the step loop
            finally:
                for p in agents.values():
                    p.send_signal(signal.SIGTERM)
                for p in agents.values():
                    p.wait(20)
                procs[1].wait(30)
                for sub in subs:
                    sub.undeclare()
        procs[0].terminate()
        procs[0].wait(10)
        # the world saw the same: its last command from robot 0 is zero
        world = json.loads((tmp_path / "out" / "world.json").read_text())
        assert world["last_cmd"]["0"]["v"] == 0.0 and world["last_cmd"]["0"]["w"] == 0.0
        assert all(p.returncode == 0 for p in agents.values())
    finally:  # whatever failed, no process of this test outlives it (a router left behind)
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)
