"""State-message latency: one host vs a fleet split over network namespaces (1 and 2 routers).

    sudo .venv/bin/python bench/multihost_latency.py [--scenario FILE] [--duration S] [--out DIR] [--tls]

Three real-time runs of the same scenario (``stack-fleet run --realtime``): everything on one host
(loopback router); one namespace per robot plus one for the world, all wired to one router
namespace; the same with two meshed router namespaces (robots split evenly: robots of
different halves reach each other through both routers). Each run's ``state_latency_ms``
(wall time from a state's publication to its arrival at each receiving agent, all pairs) is
printed as a markdown table and written to ``DIR/multihost_latency.json``. ``--tls``: every
link mTLS with the site access control (certificates made in DIR). Needs root (``ip netns``);
addresses 198.18.0.0/15 inside the namespaces only (tests/netns.py).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import yaml  # noqa: E402

from netns import Topology, agent_argv, fleet_argv, namespaces_unavailable, tag  # noqa: E402


def single_host(scenario: Path, out: Path) -> dict:
    r = subprocess.run([sys.executable, "-m", "stack.fleet", "run", str(scenario), "--realtime", "--out", str(out),
                        "--no-progress", "--no-plots"], capture_output=True, text=True, cwd=ROOT,
                       env=dict(os.environ, PYTHONUNBUFFERED="1"))
    if r.returncode not in (0, 1):
        raise SystemExit(f"single host run failed ({r.returncode}): {r.stdout}{r.stderr}")
    return json.loads((out / "report.json").read_text())


def multi_host(scenario: Path, robots: list[dict], out: Path, n_routers: int, use_tls: bool) -> dict:
    topo = Topology(tag())
    try:
        hosts = {"sim": 0, **{f"rb{r['id']}": i * n_routers // len(robots) for i, r in enumerate(robots)}}
        topo.build(n_routers, hosts)
        logs = out.parent / f"{out.name}-logs"
        logs.mkdir(parents=True, exist_ok=True)
        proto = "tls" if use_tls else "tcp"
        conf: dict[str, Path] = {}
        router_conf: dict[int, Path] = {}
        if use_tls:
            from stack.comm import tls

            pki = out.parent / f"{out.name}-pki"
            tls.make_ca(pki)
            members = {h: f"bench.{h}" for h in hosts}
            acl = tls.acl_block({"bench": list(members.values())}, [f"router.rt{j}" for j in range(n_routers)])
            for h, cn in members.items():
                tls.issue(pki, h, cn)
                conf[h] = tls.write_config(pki / f"{h}.json5", tls.tls_block(pki / "ca.pem", pki / f"{h}.pem", pki / f"{h}.key"))
            for j in range(n_routers):
                tls.issue(pki, f"rt{j}", f"router.rt{j}", ips=topo.router_addrs(j))
                router_conf[j] = tls.write_config(pki / f"rt{j}.json5",
                                                  tls.tls_block(pki / "ca.pem", pki / f"rt{j}.pem", pki / f"rt{j}.key"), acl)
        for j in range(n_routers):
            topo.router(j, logs, proto=proto, config=router_conf.get(j))
            topo.wait_router(j)
        zconf = (lambda h: ["--zenoh-config", str(conf[h])]) if use_tls else (lambda h: [])
        for r in robots:
            h = f"rb{r['id']}"
            topo.spawn(topo.hosts[h].ns, agent_argv(scenario, r, topo.endpoint(h, proto), "bench", *zconf(h)),
                       logs / f"agent-{r['id']}.log")
        argv = fleet_argv(scenario, out, topo.endpoint("sim", proto), "bench", "--realtime", "--wait-agents", "60",
                          *zconf("sim"))
        r = subprocess.run(["ip", "netns", "exec", topo.hosts["sim"].ns, *argv], capture_output=True, text=True, cwd=ROOT)
        if r.returncode not in (0, 1):
            raise SystemExit(f"{n_routers}-router run failed ({r.returncode}): {r.stdout}{r.stderr}\n{topo.logs()}")
        return json.loads((out / "report.json").read_text())
    finally:
        topo.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", type=Path, default=ROOT / "scenarios" / "four-robot-diamond.yaml")
    ap.add_argument("--duration", type=float, default=15.0, help="real-time seconds per run (default %(default)s)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "multihost_latency")
    ap.add_argument("--tls", action="store_true", help="mTLS + access control on every link")
    a = ap.parse_args(argv)
    why = namespaces_unavailable()
    if why:
        print(f"multihost_latency: {why}", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    d = yaml.safe_load(a.scenario.read_text())
    d["duration"] = a.duration
    d["success"]["max_time"] = min(d["success"].get("max_time", a.duration), a.duration)
    scenario = a.out / "scenario.yaml"
    scenario.write_text(yaml.safe_dump(d, sort_keys=False))
    rows = []
    t0 = time.monotonic()
    for name, folder, run in (
            ("single host (loopback router)", "single-host", lambda o: single_host(scenario, o)),
            ("namespaces, 1 router", "one-router", lambda o: multi_host(scenario, d["robots"], o, 1, a.tls)),
            ("namespaces, 2 meshed routers", "two-routers", lambda o: multi_host(scenario, d["robots"], o, 2, a.tls))):
        rep = run(a.out / folder)
        lat = rep["state_latency_ms"]
        rows.append({"setup": name, "p50_ms": lat["p50"], "p99_ms": lat["p99"], "samples": lat["samples"],
                     "control_loop_p99_ms": rep["control_loop_ms"]["p99"], "success": rep["success"]})
        print(f"{name}: state latency p50 {lat['p50']} ms, p99 {lat['p99']} ms ({lat['samples']} samples)", flush=True)
    (a.out / "multihost_latency.json").write_text(json.dumps({"scenario": d["name"], "duration_s": a.duration,
                                                               "tls": a.tls, "runs": rows}, indent=2))
    print(f"\n{d['name']}, {len(d['robots'])} robots, real time {a.duration:g} s per run, "
          f"{'mTLS + access control' if a.tls else 'TCP'}; {time.monotonic() - t0:.0f} s in all\n")
    print("| setup | state latency p50 [ms] | p99 [ms] | samples | control loop p99 [ms] |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['setup']} | {r['p50_ms']} | {r['p99_ms']} | {r['samples']} | {r['control_loop_p99_ms']} |")
    print(f"\nreport: {a.out / 'multihost_latency.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
