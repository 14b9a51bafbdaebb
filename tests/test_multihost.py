"""The fleet split over hosts: one network namespace per robot, per site router and for the world.

Agents reach each other only through the routers (no route between hosts, no forwarding);
``stack-fleet run --connect ... --external-agents`` runs the world and waits for agents started
elsewhere. Lock-step is deterministic, so the multi-host report must match the single-host
one. Where namespaces cannot be made these fail with the reason (see ``netns.require_namespaces``).
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest

from conftest import scenario_dict, write_scenario
from netns import Topology, agent_argv, fleet_argv, reference_report, report_differences, require_namespaces, tag

pytestmark = pytest.mark.fleet

DURATION = 6.0


def short_diamond() -> dict:
    d = scenario_dict(duration=DURATION)
    d["success"] = dict(d["success"], max_time=DURATION)
    return d


@pytest.fixture
def scenario(tmp_path: Path) -> tuple[Path, dict]:
    d = short_diamond()
    return write_scenario(tmp_path / "diamond.yaml", d), d


@pytest.fixture
def topology(request):
    require_namespaces()
    topo = Topology(tag())
    request.addfinalizer(topo.close)
    return topo


def split(robots: list[dict], n_routers: int) -> dict[str, int]:
    """Host name -> router index: the world's host on router 0, robots spread evenly."""
    hosts = {"sim": 0}
    for i, r in enumerate(robots):
        hosts[f"rb{r['id']}"] = i * n_routers // len(robots)
    return hosts


def run_multihost(topo: Topology, scenario: Path, d: dict, out: Path, n_routers: int, fleet: str,
                  agents: list[dict] | None = None, wait_agents: float = 30.0,
                  agents_up_first: bool = False) -> subprocess.CompletedProcess:
    topo.build(n_routers, split(d["robots"], n_routers))
    logs = out.parent / f"{out.name}-logs"
    logs.mkdir(parents=True, exist_ok=True)
    for j in range(n_routers):
        topo.router(j, logs)
        topo.wait_router(j)
    for r in agents if agents is not None else d["robots"]:
        host = f"rb{r['id']}"
        topo.spawn(topo.hosts[host].ns, agent_argv(scenario, r, topo.endpoint(host), fleet, "--lockstep"),
                   logs / f"agent-{r['id']}.log")
    if agents_up_first:  # every agent we started holds its liveliness token before the orchestrator looks
        for r in agents if agents is not None else d["robots"]:
            wait_log(logs / f"agent-{r['id']}.log", ") up on ", topo)
    argv = fleet_argv(scenario, out, topo.endpoint("sim"), fleet, "--wait-agents", f"{wait_agents:g}")
    return subprocess.run(["ip", "netns", "exec", topo.hosts["sim"].ns, *argv], capture_output=True, text=True, timeout=150)


def wait_log(path: Path, text: str, topo: Topology, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and text in path.read_text(errors="replace"):
            return
        time.sleep(0.1)
    raise AssertionError(f"{path.name}: no {text!r} within {timeout:.0f} s\n{topo.logs()}")


def test_hosts_reach_each_other_only_through_routers(topology: Topology):
    topology.build(2, {"rb0": 0, "rb1": 0, "rb2": 1})
    # nothing listens yet: the router's address answers (refused), the other robots' are unreachable
    assert topology.tcp_reachable(topology.hosts["rb0"].ns, topology.hosts["rb0"].router_addr) == "ECONNREFUSED"
    for other in ("rb1", "rb2"):
        assert topology.tcp_reachable(topology.hosts["rb0"].ns, topology.hosts[other].addr) == "ENETUNREACH"
    # and router 1 is reachable only from router 0's side of the mesh link, not from a robot of router 0
    assert topology.tcp_reachable(topology.hosts["rb0"].ns, topology.router_links[1][1]) == "ENETUNREACH"
    assert topology.tcp_reachable(topology.routers[0], topology.router_links[1][1]) == "ECONNREFUSED"


@pytest.mark.parametrize("n_routers", [1, 2])
def test_fleet_over_namespaces_matches_single_host(tmp_path: Path, scenario, topology: Topology, n_routers: int):
    path, d = scenario
    ref = reference_report(path, tmp_path / "single-host")
    out = tmp_path / f"multihost-{n_routers}"
    t0 = time.monotonic()
    proc = run_multihost(topology, path, d, out, n_routers, fleet=f"mh{n_routers}")
    assert proc.returncode == (0 if ref["success"] else 1), proc.stdout + proc.stderr + topology.logs()
    rep = json.loads((out / "report.json").read_text())
    assert rep["mode"] == "lockstep" and rep["steps"] == ref["steps"] > 50
    assert report_differences(ref, rep) == [], topology.logs()
    assert rep["crashed"] == [] and rep["comm"]["malformed"] == 0
    assert rep["state_latency_ms"]["samples"] > 0
    # lock-step agents end by themselves once the world is done
    deadline = time.monotonic() + 15
    agents = [p for log, p in topology.procs if "agent-" in log]
    while time.monotonic() < deadline and any(p.poll() is None for p in agents):
        time.sleep(0.1)
    assert [p.poll() for p in agents] == [0] * len(agents), topology.logs()
    assert time.monotonic() - t0 < 120


def test_external_agents_that_never_come_up_are_named(tmp_path: Path, scenario, topology: Topology):
    path, d = scenario
    out = tmp_path / "missing"
    proc = run_multihost(topology, path, d, out, 1, fleet="mhmissing", agents=d["robots"][:3], wait_agents=2,
                         agents_up_first=True)
    assert proc.returncode == 3, proc.stdout + proc.stderr
    assert "robots [3] never came up" in proc.stdout + proc.stderr, proc.stdout + proc.stderr
    assert "mhmissing" in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert "within 2 s" in proc.stdout
    rep = json.loads((out / "report.json").read_text())
    assert rep["crashed"][0]["process"] == "agents"
