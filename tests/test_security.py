"""Mutual TLS and zenoh access control: certificates made here, real handshakes, real denials.

A site router (``stack-router`` with a ``deploy/``-shaped config: mTLS + deny-by-default ACL)
admits only sessions whose certificate its CA signed, and lets a fleet's members (their
certificates' common names) use only ``stack/<fleet>/**``. The loopback tests need no
namespaces; the fleet run under TLS is split over namespaces (it fails, with the reason, where they
cannot be made: see ``netns.require_namespaces``).
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from conftest import ROOT, run_cli, scenario_dict, write_scenario
from netns import Topology, agent_argv, fleet_argv, reference_report, report_differences, require_namespaces, tag
from stack.comm import tls
from stack.comm.session import ConfigFileError, EndpointError, SessionConfig, SessionError, open_session, zenoh_config
from stack.scenario import load_scenario

FLEET_A, FLEET_B = "fleetA", "fleetB"


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    """A site CA with a router, two fleet-A members and one fleet-B member; and a rogue CA."""
    d = tmp_path_factory.mktemp("pki")
    tls.make_ca(d)
    tls.issue(d, "router", "router.site")
    tls.issue(d, "a0", f"{FLEET_A}.robot-0")
    tls.issue(d, "a1", f"{FLEET_A}.robot-1")
    tls.issue(d, "b0", f"{FLEET_B}.robot-0")
    rogue = d / "rogue"
    tls.make_ca(rogue, "someone else's CA")
    tls.issue(rogue, "a0", f"{FLEET_A}.robot-0")  # the right name, the wrong signer
    return d


def client_config(pki: Path, name: str, folder: Path | None = None) -> Path:
    folder = folder or pki
    return tls.write_config(pki / f"{folder.name}-{name}.json5",
                            tls.tls_block(pki / "ca.pem", folder / f"{name}.pem", folder / f"{name}.key"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_router(pki: Path, acl: bool, log: Path) -> tuple[subprocess.Popen, str]:
    fleets = {FLEET_A: [f"{FLEET_A}.robot-0", f"{FLEET_A}.robot-1"], FLEET_B: [f"{FLEET_B}.robot-0"]}
    conf = tls.write_config(pki / f"router-{'acl' if acl else 'open'}.json5",
                            tls.tls_block(pki / "ca.pem", pki / "router.pem", pki / "router.key"),
                            tls.acl_block(fleets, ["router.site"]) if acl else None)
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    fh = open(log, "wb")
    p = subprocess.Popen([sys.executable, "-m", "stack.comm.router", "--listen", ep, "--config", str(conf)],
                         stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT)
    fh.close()
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        assert p.poll() is None, log.read_text()
        try:
            socket.create_connection(("127.0.0.1", port), 0.2).close()
            return p, ep
        except OSError:
            time.sleep(0.05)
    p.kill()
    raise TimeoutError(f"router did not open {ep}: {log.read_text()}")


@pytest.fixture
def secure_router(pki: Path, tmp_path: Path, request):
    """Start a TLS router (``acl=True``: with the site's access control); stopped at the end of the test."""
    started = []

    def start(acl: bool = True) -> str:
        p, ep = start_router(pki, acl, tmp_path / f"router-{len(started)}.log")
        started.append(p)
        return ep

    def stop():
        for p in started:
            p.terminate()
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)

    request.addfinalizer(stop)
    return start


def session(ep: str, conf: Path) -> zenoh.Session:
    return open_session(SessionConfig(connect=[ep], config_file=str(conf)))


def test_session_without_a_valid_certificate_is_refused(pki: Path, secure_router, tmp_path: Path):
    ep = secure_router()
    with session(ep, client_config(pki, "a0")):  # the control: a member's certificate opens
        pass
    no_cert = tls.write_config(tmp_path / "no-cert.json5", {"root_ca_certificate": str(pki / "ca.pem")})
    refused = {
        "no client certificate": (ep, no_cert),
        "certificate from another CA": (ep, client_config(pki, "a0", pki / "rogue")),
        "plain TCP to the TLS port": (ep.replace("tls/", "tcp/"), None),
    }
    for why, (endpoint, conf) in refused.items():
        with pytest.raises(SessionError, match="cannot reach a Zenoh router"):
            s = open_session(SessionConfig(connect=[endpoint], config_file=str(conf) if conf else None))
            s.close()
            pytest.fail(f"{why}: the session opened")
    # the agent's command line says so in one line and exits 1
    sc = write_scenario(tmp_path / "d.yaml", scenario_dict())
    r = run_cli(["stack-agent", "--id", "1", "--scenario", str(sc), "--connect", ep, "--fleet", FLEET_A,
                 "--zenoh-config", str(client_config(pki, "a0", pki / "rogue"))], timeout=60)
    assert r.returncode == 1 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.startswith("stack-agent: cannot reach a Zenoh router at " + ep), r.stderr


def _exchange(ep: str, pki: Path) -> dict[str, list]:
    """Fleet B's member tries to publish into fleet A (cmd_vel, state, a liveliness token) and to listen to it."""
    got: dict[str, list] = {"a": [], "a_alive": [], "b": [], "b_spy": []}
    lock = threading.Lock()

    def sink(name):
        def cb(sample):
            with lock:
                got[name].append((str(sample.key_expr), bytes(sample.payload.to_bytes())))
        return cb

    with session(ep, client_config(pki, "a0")) as a0, session(ep, client_config(pki, "a1")) as a1, \
            session(ep, client_config(pki, "b0")) as b0:
        subs = [a0.declare_subscriber(f"stack/{FLEET_A}/*/cmd_vel", sink("a")),
                a0.declare_subscriber(f"stack/{FLEET_A}/*/state", sink("a")),
                a0.liveliness().declare_subscriber(f"stack/{FLEET_A}/alive/*", sink("a_alive")),
                b0.declare_subscriber(f"stack/{FLEET_B}/**", sink("b"))]
        b_spy = b0.declare_subscriber(f"stack/{FLEET_A}/**", sink("b_spy"))
        time.sleep(0.5)
        token = b0.liveliness().declare_token(f"stack/{FLEET_A}/alive/7")
        member_token = a1.liveliness().declare_token(f"stack/{FLEET_A}/alive/1")
        for i in range(10):
            b0.put(f"stack/{FLEET_A}/1/cmd_vel", b"intruder")
            b0.put(f"stack/{FLEET_A}/1/state", b"intruder")
            a1.put(f"stack/{FLEET_A}/1/cmd_vel", b"member")
            a1.put(f"stack/{FLEET_A}/1/state", b"member")
            b0.put(f"stack/{FLEET_B}/0/cmd_vel", b"own fleet")
            time.sleep(0.02)
        time.sleep(0.7)
        for x in (token, member_token, b_spy, *subs):
            x.undeclare()
    with lock:
        return {k: list(v) for k, v in got.items()}


def test_other_fleet_cannot_publish_into_this_fleet(pki: Path, secure_router):
    got = _exchange(secure_router(acl=True), pki)
    payloads = {k: {p for _, p in v} for k, v in got.items()}
    assert payloads["a"] == {b"member"} and len(got["a"]) == 20, got["a"][:5]   # members get through, both keys
    assert payloads["b"] == {b"own fleet"} and len(got["b"]) == 10              # fleet B works in its own prefix
    alive = {k for k, _ in got["a_alive"]}
    assert f"stack/{FLEET_A}/alive/1" in alive and f"stack/{FLEET_A}/alive/7" not in alive, alive
    # fleet B's subscription to fleet A's keys gets nothing of fleet A's (only its own local puts, never routed)
    assert b"member" not in payloads["b_spy"], got["b_spy"][:5]
    # the control: the same exchange through a router with TLS but no access control lets the intruder in,
    # so the denial above is the access control's doing
    open_got = _exchange(secure_router(acl=False), pki)
    assert b"intruder" in {p for _, p in open_got["a"]}
    assert f"stack/{FLEET_A}/alive/7" in {k for k, _ in open_got["a_alive"]}
    assert b"member" in {p for _, p in open_got["b_spy"]}


def test_bad_zenoh_config_is_one_line_error(tmp_path: Path, pki: Path):
    sc = write_scenario(tmp_path / "d.yaml", scenario_dict())
    (tmp_path / "broken.json5").write_text('{ mode: "client", connect: { endpoints: [\n')
    (tmp_path / "unknown.json5").write_text("{ no_such_section: 1 }\n")
    missing_cert = tls.write_config(tmp_path / "missing-cert.json5",
                                    tls.tls_block(pki / "ca.pem", tmp_path / "gone.pem", tmp_path / "gone.key"))
    cases = {"broken.json5": "line 2, column 1", "unknown.json5": "unknown field",
             "nonexistent.json5": "No such file", missing_cert.name: "no such file"}
    for name, what in cases.items():
        with pytest.raises(ConfigFileError, match=what):
            open_session(SessionConfig(connect=["tls/127.0.0.1:9"], config_file=str(tmp_path / name)))
    # the command lines (started together: each costs an interpreter start)
    runs = []
    for i, (name, what) in enumerate(cases.items()):
        path = str(tmp_path / name)
        argv = (["-m", "stack.agents", "--id", "1", "--scenario", str(sc), "--zenoh-config", path] if i % 2 else
                ["-m", "stack.comm.router", "--listen", f"tcp/127.0.0.1:{free_port()}", "--config", path])
        runs.append((path, what, subprocess.Popen([sys.executable, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                                  text=True, cwd=ROOT)))
    for path, what, p in runs:
        _, err = p.communicate(timeout=60)
        assert p.returncode != 0 and "Traceback" not in err, err
        assert err.count("\n") == 1 and what in err and path in err, err


def test_deploy_files_are_valid(tmp_path: Path, pki: Path):
    """Every zenoh config in deploy/ parses with zenoh itself, keeps multicast scouting off and names its endpoints;
    every robot config is a scenario the loader accepts."""
    confs = sorted((ROOT / "deploy").rglob("*.json5"))
    assert len(confs) >= 3, confs
    routers = 0
    for path in confs:
        conf = zenoh.Config.from_file(str(path))
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False, path
        mode = json.loads(conf.get_json("mode"))
        endpoints = json.loads(conf.get_json("connect/endpoints")) + json.loads(conf.get_json("listen/endpoints"))
        assert endpoints and all("/" in e and ":" in e for e in endpoints), (path, endpoints)
        if mode == "router":
            routers += 1
            assert json.loads(conf.get_json("access_control/enabled")) is True, path
            assert json.loads(conf.get_json("access_control/default_permission")) == "deny", path
        assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True, path
    assert routers >= 1, confs  # the routers' access control above was checked on at least one
    robots = sorted((ROOT / "deploy" / "robots").glob("*.yaml"))
    assert {r.name for r in robots} >= {"jackal-can.yaml", "rover-mavlink.yaml"}
    drivers = {}
    for path in robots:
        sc = load_scenario(str(path))
        drivers.update({r.driver: r.driver_params.get(r.driver, {}) for r in sc.robots})
    assert drivers["can"]["interface"] == "socketcan" and drivers["can"]["channel"] == "can0"
    assert drivers["mavlink"]["connection"].startswith("/dev/")
    # the site router's file, with this test's certificates, layers under stack-router's command line:
    # our --listen replaces the file's, the file's mesh endpoints stay, and only with --allow-remote
    site = (ROOT / "deploy" / "zenoh" / "site-router.json5").read_text().replace("/etc/stack/certs", str(pki))
    for name in ("router-a", "router-b"):
        site = site.replace(f"{name}.pem", "router.pem").replace(f"{name}.key", "router.key")
    (tmp_path / "site.json5").write_text(site)
    cfg = SessionConfig(mode="router", listen=["tls/127.0.0.1:7447"], config_file=str(tmp_path / "site.json5"))
    with pytest.raises(EndpointError, match="192.0.2.2"):
        zenoh_config(cfg)
    cfg.allow_remote = True
    conf = zenoh_config(cfg)
    assert json.loads(conf.get_json("listen/endpoints")) == ["tls/127.0.0.1:7447"]
    assert json.loads(conf.get_json("connect/endpoints")) == ["tls/192.0.2.2:7447"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    unit = (ROOT / "deploy" / "systemd" / "stack-agent@.service").read_text()
    assert "ExecStart=" in unit and "--zenoh-config" in unit and "KillSignal=SIGINT" in unit


# ---- the fleet under mTLS + access control, split over namespaces, with an intruder of another fleet ----

INTRUDER = """
import sys, time
from stack.comm.session import SessionConfig, open_session
with open_session(SessionConfig(connect=[sys.argv[1]], config_file=sys.argv[2], allow_remote=True)) as s:
    print("connected", flush=True)
    pubs = [s.declare_publisher(f"stack/{sys.argv[3]}/{i}/{t}") for i in range(4) for t in ("cmd_vel", "state", "odom")]
    n = 0
    while True:
        for p in pubs:
            p.put(b"\\xc1 not msgpack")
            n += 1
        if n % 1200 == 0:
            print("sent", n, flush=True)
        time.sleep(0.01)
"""


@pytest.mark.fleet
def test_fleet_runs_under_mtls_and_access_control(tmp_path: Path, request):
    require_namespaces()
    d = scenario_dict(duration=6.0)
    d["success"] = dict(d["success"], max_time=6.0)
    scenario = write_scenario(tmp_path / "diamond.yaml", d)
    ref = reference_report(scenario, tmp_path / "single-host")

    topo = Topology(tag())
    request.addfinalizer(topo.close)
    hosts = {"sim": 0, "intruder": 0, "rb0": 0, "rb1": 0, "rb2": 1, "rb3": 1}
    topo.build(2, hosts)
    pki = tmp_path / "pki"
    tls.make_ca(pki)
    members = {"sim": f"{FLEET_A}.sim", **{f"rb{i}": f"{FLEET_A}.robot-{i}" for i in range(4)}}
    conf: dict[str, Path] = {}
    for host, cn in {**members, "intruder": f"{FLEET_B}.robot-0"}.items():
        tls.issue(pki, host, cn)
        conf[host] = tls.write_config(pki / f"{host}.json5", tls.tls_block(pki / "ca.pem", pki / f"{host}.pem", pki / f"{host}.key"))
    acl = tls.acl_block({FLEET_A: sorted(members.values()), FLEET_B: [f"{FLEET_B}.robot-0"]}, ["router.rt0", "router.rt1"])
    logs = tmp_path / "logs"
    logs.mkdir()
    for j in range(2):
        tls.issue(pki, f"rt{j}", f"router.rt{j}", ips=topo.router_addrs(j))
        rconf = tls.write_config(pki / f"rt{j}.json5", tls.tls_block(pki / "ca.pem", pki / f"rt{j}.pem", pki / f"rt{j}.key"), acl)
        topo.router(j, logs, proto="tls", config=rconf)
        topo.wait_router(j)
    intruder = topo.spawn(topo.hosts["intruder"].ns, [sys.executable, "-c", INTRUDER, topo.endpoint("intruder", "tls"),
                                                      str(conf["intruder"]), FLEET_A], logs / "intruder.log")
    for r in d["robots"]:
        host = f"rb{r['id']}"
        topo.spawn(topo.hosts[host].ns, agent_argv(scenario, r, topo.endpoint(host, "tls"), FLEET_A, "--lockstep",
                                                   "--zenoh-config", str(conf[host])), logs / f"agent-{r['id']}.log")
    out = tmp_path / "secure"
    proc = subprocess.run(["ip", "netns", "exec", topo.hosts["sim"].ns,
                           *fleet_argv(scenario, out, topo.endpoint("sim", "tls"), FLEET_A, "--wait-agents", "30",
                                       "--zenoh-config", str(conf["sim"]))], capture_output=True, text=True, timeout=150)
    assert proc.returncode == (0 if ref["success"] else 1), proc.stdout + proc.stderr + topo.logs()
    rep = json.loads((out / "report.json").read_text())
    assert report_differences(ref, rep) == [], topo.logs()
    assert rep["comm"]["malformed"] == 0 and rep["crashed"] == []  # not one of the intruder's messages got in
    intr_log = (logs / "intruder.log").read_text()
    assert intruder.poll() is None and "connected" in intr_log and "sent" in intr_log, intr_log  # it was in, and trying
