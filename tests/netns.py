"""Test hosts in Linux network namespaces: one per robot, one per site router, veth links.

Every namespace and link here is made by the test run and removed by it (also on failure:
:meth:`Topology.close` is a fixture finalizer). Addresses are from the benchmarking range
198.18.0.0/15 and exist only inside these namespaces; the namespaces have no route to the
host's interfaces and no forwarding, so a host reaches another only through a router
*process* (zenoh), never through the kernel:

- host link k (host <-> its router): router side 198.18.k.1/24, host side 198.18.k.2/24
- router link j (router 0 <-> router j): 198.19.j.1/24 on router 0, 198.19.j.2/24 on router j

Routers listen on PORT on every address of their namespace.
"""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from stack.fleet.orchestrator import ZENOH_RUNTIME

ROOT = Path(__file__).resolve().parents[1]
PORT = 7447
_counter = [0]


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


def namespaces_unavailable() -> str | None:
    """None if this process can make a network namespace with a veth link (tried), else why not."""
    name = f"probe{os.getpid()}"
    try:
        r = _ip("netns", "add", name, check=False)
        if r.returncode != 0:
            return f"cannot create network namespaces here (ip netns add: {r.stderr.strip() or r.returncode})"
        r = _ip("-n", name, "link", "add", "a0", "type", "veth", "peer", "name", "b0", check=False)
        if r.returncode != 0:
            return f"cannot create veth links in a network namespace ({r.stderr.strip()})"
        return None
    except (OSError, subprocess.SubprocessError) as e:
        return f"cannot create network namespaces here ({e})"
    finally:
        subprocess.run(["ip", "netns", "del", name], capture_output=True)


@functools.lru_cache(maxsize=1)
def _why_not() -> str | None:
    return namespaces_unavailable()


def require_namespaces() -> None:
    """Tests on network namespaces fail, with the reason, where namespaces cannot be made (they need root
    and iproute2): no silent skip on the CI path. ``STACK_TESTS_WITHOUT_NETNS=1`` declares a machine that
    cannot, and skips them by name; ``pytest -m "not fleet"`` leaves them out too."""
    why = _why_not()
    if why is None:
        return
    if os.environ.get("STACK_TESTS_WITHOUT_NETNS") == "1":
        pytest.skip(f"{why} (STACK_TESTS_WITHOUT_NETNS=1)")
    pytest.fail(f"{why}; run as root with iproute2, or deselect with -m 'not fleet', or set STACK_TESTS_WITHOUT_NETNS=1",
                pytrace=False)


def tag() -> str:
    _counter[0] += 1
    return f"fs{os.getpid()}x{_counter[0]}"


@dataclass
class Host:
    name: str
    ns: str
    router: int          # index of the router it is wired to
    addr: str            # its own address
    router_addr: str     # the router's address on its link


@dataclass
class Topology:
    """Routers and hosts in namespaces named ``<tag>-...``; build with :meth:`build`, end with :meth:`close`."""

    tag: str
    routers: list[str] = field(default_factory=list)          # namespace per router
    router_links: dict[int, tuple[str, str]] = field(default_factory=dict)  # j -> (addr on router 0, addr on router j)
    hosts: dict[str, Host] = field(default_factory=dict)
    procs: list[tuple[str, subprocess.Popen]] = field(default_factory=list)
    _made: list[str] = field(default_factory=list)

    def _ns(self, name: str) -> str:
        ns = f"{self.tag}-{name}"
        _ip("netns", "add", ns)
        self._made.append(ns)
        _ip("-n", ns, "link", "set", "lo", "up")
        subprocess.run(["ip", "netns", "exec", ns, "sysctl", "-qw", "net.ipv4.ip_forward=0"], capture_output=True, check=True)
        return ns

    @staticmethod
    def _link(ns_a: str, if_a: str, addr_a: str, ns_b: str, if_b: str, addr_b: str) -> None:
        _ip("-n", ns_a, "link", "add", if_a, "type", "veth", "peer", "name", if_b, "netns", ns_b)
        for ns, ifn, addr in ((ns_a, if_a, addr_a), (ns_b, if_b, addr_b)):
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", ifn)
            _ip("-n", ns, "link", "set", ifn, "up")

    def build(self, n_routers: int, hosts: dict[str, int]) -> "Topology":
        """``n_routers`` router namespaces (router j>0 linked to router 0) and one namespace per host."""
        for j in range(n_routers):
            self.routers.append(self._ns(f"rt{j}"))
        for j in range(1, n_routers):
            a, b = f"198.19.{j}.1", f"198.19.{j}.2"
            self._link(self.routers[0], f"mesh{j}", a, self.routers[j], "mesh0", b)
            self.router_links[j] = (a, b)
        for k, (name, j) in enumerate(hosts.items()):
            ns = self._ns(name)
            r_addr, h_addr = f"198.18.{k}.1", f"198.18.{k}.2"
            self._link(self.routers[j], f"h{k}", r_addr, ns, "up0", h_addr)
            self.hosts[name] = Host(name, ns, j, h_addr, r_addr)
        return self

    def router_addrs(self, j: int) -> list[str]:
        """Every address router j has (for its certificate's names)."""
        out = [h.router_addr for h in self.hosts.values() if h.router == j]
        if j == 0:
            out += [a for a, _ in self.router_links.values()]
        elif j in self.router_links:
            out.append(self.router_links[j][1])
        return out

    def endpoint(self, host: str, proto: str = "tcp") -> str:
        """The endpoint ``host`` uses to reach its router."""
        return f"{proto}/{self.hosts[host].router_addr}:{PORT}"

    def spawn(self, ns: str, argv: list[str], log: Path, env: dict | None = None) -> subprocess.Popen:
        """Start ``argv`` inside namespace ``ns`` (stdout+stderr to ``log``); stopped by :meth:`close`."""
        full_env = dict(os.environ, PYTHONUNBUFFERED="1")
        full_env.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)  # as stack-fleet does for the processes it starts
        full_env.update(env or {})
        fh = open(log, "wb")
        p = subprocess.Popen(["ip", "netns", "exec", ns, *argv], stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT,
                             env=full_env, start_new_session=True)
        fh.close()
        self.procs.append((str(log), p))
        return p

    def router(self, j: int, log_dir: Path, proto: str = "tcp", config: Path | None = None) -> subprocess.Popen:
        """Start router j (listening on every address of its namespace; router j>0 connects to router 0)."""
        argv = [sys.executable, "-m", "stack.comm.router", "--listen", f"{proto}/0.0.0.0:{PORT}", "--allow-remote"]
        if j > 0:
            argv += ["--connect", f"{proto}/{self.router_links[j][0]}:{PORT}"]
        if config is not None:
            argv += ["--config", str(config)]
        return self.spawn(self.routers[j], argv, log_dir / f"router{j}.log")

    def wait_router(self, j: int, timeout: float = 10.0) -> None:
        """Until router j accepts TCP on its first address (seen from inside its namespace)."""
        addr = self.router_addrs(j)[0]
        code = (f"import socket,sys\ntry:\n socket.create_connection(('{addr}', {PORT}), 0.3).close()\n"
                f"except OSError: sys.exit(1)")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.can_run(self.routers[j], code):
                return
            time.sleep(0.1)
        raise TimeoutError(f"router {j} did not open {addr}:{PORT} within {timeout:.0f} s")

    @staticmethod
    def can_run(ns: str, code: str) -> bool:
        return subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", code], capture_output=True,
                              timeout=20).returncode == 0

    def tcp_reachable(self, ns: str, addr: str, port: int = PORT) -> str:
        """'ok', or the errno name of a TCP connect from ``ns`` to ``addr:port``."""
        code = (f"import socket,errno\ntry:\n socket.create_connection(('{addr}', {port}), 1.0).close(); print('ok')\n"
                f"except OSError as e: print(errno.errorcode.get(e.errno, str(e)) if e.errno else type(e).__name__)")
        r = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", code], capture_output=True, text=True, timeout=20)
        return r.stdout.strip()

    def close(self) -> None:
        """Stop every process started here (SIGTERM, then SIGKILL) and anything left in our namespaces, then remove them."""
        for _, p in self.procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + 10
        for _, p in self.procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(5)
        for ns in self._made:  # anything a started process left behind inside our namespaces
            r = _ip("netns", "pids", ns, check=False)
            for pid in r.stdout.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
        for ns in reversed(self._made):
            _ip("netns", "del", ns, check=False)
        self._made.clear()

    def logs(self) -> str:
        """The last lines of every process's log (for assertion messages)."""
        out = []
        for path, p in self.procs:
            try:
                tail = Path(path).read_text(errors="replace").strip().splitlines()[-4:]
            except OSError:
                tail = []
            out.append(f"--- {Path(path).name} (exit {p.poll()}):\n" + "\n".join(tail))
        return "\n".join(out)


def agent_argv(scenario: Path, robot: dict, endpoint: str, fleet: str, *extra: str) -> list[str]:
    argv = [sys.executable, "-m", "stack.agents", "--id", str(robot["id"]), "--scenario", str(scenario),
            "--connect", endpoint, "--fleet", fleet, "--allow-remote", "--log-level", "INFO", *extra]
    if robot.get("role"):
        argv += ["--role", robot["role"]]
    return argv


def fleet_argv(scenario: Path, out: Path, endpoint: str, fleet: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "stack.fleet", "run", str(scenario), "--out", str(out), "--no-progress", "--no-plots",
            "--connect", endpoint, "--external-agents", "--fleet", fleet, "--allow-remote", *extra]


# what a lock-step run must reproduce whatever the hosts and routers (deterministic); timing fields excluded
COMPARED = ("success", "sim_time_s", "steps", "leader_time_to_goal_s", "collisions", "min_robot_distance_m",
            "min_obstacle_distance_m", "max_robot_distance_m", "connectivity", "formation_error_rms_m")
PER_ROBOT = ("path_length_m", "final_error_m", "estimator_rmse_m", "error_convergence_time_s", "situations")


def report_differences(ref: dict, rep: dict, tol: float = 1e-3) -> list[str]:
    """Where ``rep`` differs from ``ref`` beyond ``tol`` (absolute, on numbers)."""
    def same(a, b) -> bool:
        if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
            return abs(a - b) <= tol
        if isinstance(a, dict) and isinstance(b, dict):
            return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
        return a == b

    diffs = [f"{k}: {ref.get(k)!r} vs {rep.get(k)!r}" for k in COMPARED if not same(ref.get(k), rep.get(k))]
    for rid, r in ref["robots"].items():
        other = rep.get("robots", {}).get(rid, {})
        diffs += [f"robots.{rid}.{k}: {r.get(k)!r} vs {other.get(k)!r}" for k in PER_ROBOT if not same(r.get(k), other.get(k))]
    for k in ("sent", "delivered", "malformed"):
        if ref["comm"].get(k) != rep.get("comm", {}).get(k):
            diffs.append(f"comm.{k}: {ref['comm'].get(k)} vs {rep.get('comm', {}).get(k)}")
    return diffs


_REFERENCE: dict[str, dict] = {}


def reference_report(scenario: Path, out: Path) -> dict:
    """The single-host run of ``scenario`` (``stack-fleet run``: its own loopback router and agents), once per session."""
    key = scenario.read_text()
    if key not in _REFERENCE:
        r = subprocess.run([sys.executable, "-m", "stack.fleet", "run", str(scenario), "--out", str(out), "--no-progress",
                            "--no-plots"], capture_output=True, text=True, timeout=180, cwd=ROOT,
                           env=dict(os.environ, PYTHONUNBUFFERED="1"))
        rep = json.loads((out / "report.json").read_text())
        assert r.returncode == (0 if rep["success"] else 1) and rep["crashed"] == [], r.stdout + r.stderr
        _REFERENCE[key] = rep
    return _REFERENCE[key]
