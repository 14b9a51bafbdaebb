"""Fleet benchmark: steps/s against its floors and IR-SIM, real time, and memory per agent, for 4-32 robots.

For each fleet size, ``--rounds`` times (the order reversed every other round, so that the
machine's drift biases no column; the table gives each column's median), in one run:

- our whole multi-process fleet (router + world + one agent process per robot, PID, dt = 0.1 s)
  in lock-step;
- **the world floor**: the world's own step (``stack.sim_bridge.server.WorldServer``: truth log,
  lidar with culling, odometry, IMU, encoding and publishing every message to a router, physics)
  for the same robots and beams, with no agent: it replays the commands the fleet's robots sent
  (``truth.npz``), so it does the very same world work;
- **the ray floor**: pybullet alone, every beam of every robot cast (no culling) in one
  ``rayTestBatch`` a step, plus the bodies' motion (``stack.sim_bridge.world.World``);
- IR-SIM, single process, the same robots, lidars and obstacles (``bench/irsim_peer.py``;
  ``pip install -e '.[bench]'``).

Then one real-time run per size, and the memory of every agent process (``stack.fleet.procmem``:
PSS, the fair share of shared pages; RSS and USS beside it) in a lock-step fleet of
``--memory-size`` robots with PID and with DRL (numpy runtime, the default), sampled in their own
runs so that reading /proc does not slow the timed ones. Prints the tables with the issue's
ratios (fleet / world floor >= 0.6, fleet / IR-SIM >= 2) and writes them with the raw numbers
to ``--out``.

    python bench/fleet_bench.py                       # 4, 8, 16, 32 robots
    python bench/fleet_bench.py --sizes 4 32 --lockstep-s 30 --realtime-s 20 --rounds 3
    python bench/fleet_bench.py --tiny                # a minute: shows that it works, numbers meaningless
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stack.fleet.orchestrator import ZENOH_RUNTIME, Fleet, FleetConfig, run_fleet, sigterm_as_interrupt  # noqa: E402
from stack.fleet.procmem import Sampler  # noqa: E402
from stack.fleet.procs import Proc  # noqa: E402
from stack.scenario import parse_scenario  # noqa: E402

os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)  # the world floor's session as the fleet's world process has it


def fleet_scenario(n: int, duration: float) -> dict:
    """A leader and n-1 followers on a grid behind it (2 m apart), cylinders along both sides of the path."""
    slots, robots = {}, [{"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0]}]
    cols = 4
    for i in range(1, n):
        row, col = divmod(i - 1, cols)
        dx, dy = -2.0 * (row + 1), 2.0 * (col - (cols - 1) / 2)
        slots[i] = {"L": round(math.hypot(dx, dy), 6), "psi_deg": round(math.degrees(math.atan2(dy, dx)), 6)}
        robots.append({"id": i, "role": "follower", "pose": [dx, dy, 0.0]})
    obstacles = [{"type": "cylinder", "x": 6.0 * k, "y": s * 7.0, "radius": 0.6} for k in range(1, 12) for s in (-1, 1)]
    return {
        "name": f"bench-{n}", "seed": 0, "dt": 0.1, "duration": duration,
        "world": {"obstacles": obstacles},
        "robot": {"radius": 0.5, "v_max": 1.0, "w_max": 1.0, "lidar": {"beams": 180, "fov_deg": 180, "range": 5.0, "noise_std": 0.01},
                  "comm_range": 10.0},
        "formation": {"leader": 0, "goal": [500.0, 0.0], "slots": slots},
        "robots": robots,
        "success": {"goal_tolerance": 0.5, "no_collisions": False},
    }


def run_ours(n: int, out: Path, duration: float, realtime: bool) -> dict:
    data = fleet_scenario(n, duration)
    path = out / f"bench-{n}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    sc = parse_scenario(data, str(path))
    mode = "realtime" if realtime else "lockstep"
    code, rep = run_fleet(FleetConfig(scenario=sc, out=out / f"{mode}-{n}", realtime=realtime, progress=False, plots=False))
    world = json.loads((out / f"{mode}-{n}" / "world.json").read_text())
    sps = world.get("steps_per_s") or 0.0
    return {"robots": n, "mode": mode, "exit": code, "steps": world.get("steps"), "steps_per_s": sps,
            "rtf": sps * sc.dt, "loop_p50_ms": rep["control_loop_ms"]["p50"], "loop_p99_ms": rep["control_loop_ms"]["p99"],
            "compute_p50_ms": rep["control_compute_ms"]["p50"], "compute_p99_ms": rep["control_compute_ms"]["p99"],
            "state_p50_ms": rep["state_latency_ms"]["p50"], "state_p99_ms": rep["state_latency_ms"]["p99"],
            "late_steps": world.get("late_steps"), "scenario": str(path)}


def _commands(run_dir: Path) -> list[dict[int, tuple[float, float]]]:
    """The command each robot's world step took, step by step, from a fleet run's ``truth.npz``."""
    z = np.load(run_dir / "truth.npz")
    ids = [int(i) for i in z["ids"]]
    return [{rid: (float(v[j]), float(w[j])) for j, rid in enumerate(ids)} for v, w in zip(z["cmd_v"][:-1], z["cmd_w"][:-1])]


def world_floor(sc, commands: list[dict], endpoint: str) -> dict:
    """The world process's step without agents (WorldServer's own truth log, sensors, encoding, publishing to the
    router at ``endpoint``, physics), replaying ``commands``; steps/s of that loop."""
    from stack.comm.session import SessionConfig, open_session
    from stack.sim_bridge.server import WorldConfig, WorldServer

    with open_session(SessionConfig(mode="client", connect=[endpoint])) as session:
        srv = WorldServer(WorldConfig(scenario=sc, connect=endpoint, fleet=f"floor{os.getpid()}"), session)
        k = srv.keys
        pubs = {(rid, t): session.declare_publisher(k.robot(rid, t)) for rid in srv.ids for t in ("odom", "imu", "scan", "fix")}
        clock_pub, truth_pub = session.declare_publisher(k.world("clock")), session.declare_publisher(k.world("truth"))
        rows: dict[str, list] = {key: [] for key in ("t", "x", "y", "yaw", "v", "w", "alive")}
        alive = set(srv.ids)
        t0 = time.perf_counter()
        for srv.k, cmd in enumerate(commands):
            srv.t = srv.k * sc.dt
            srv._log_truth(rows, alive)
            srv._publish_step(pubs, clock_pub, truth_pub, [], [], t0)
            srv._advance(cmd)
        wall = time.perf_counter() - t0
        srv.world.close()
    return {"steps": len(commands), "steps_per_s": len(commands) / wall, "rays_cast": srv.world.rays_cast}


def ray_floor(sc, commands: list[dict]) -> dict:
    """pybullet alone: every beam of every robot (no culling) in one rayTestBatch a step, and the motion."""
    from stack.sim_bridge.world import World

    w = World(sc)
    w.cull = False
    t0 = time.perf_counter()
    for cmd in commands:
        w.lidar()
        w.step(cmd, sc.dt)
    wall = time.perf_counter() - t0
    w.close()
    return {"steps": len(commands), "steps_per_s": len(commands) / wall, "rays_cast": w.rays_cast}


def memory(n: int, policy: str, out: Path, duration: float) -> dict:
    """Peak PSS / RSS / USS [MB] of each agent process of a lock-step fleet of ``n`` robots on ``policy``."""
    data = fleet_scenario(n, duration)
    data["robot"]["policy"] = policy
    sc = parse_scenario(data, f"memory-{policy}-{n}.yaml")
    with Sampler(Proc, period_s=0.5) as s:
        code, rep = Fleet(FleetConfig(scenario=sc, out=out / f"memory-{policy}-{n}", progress=False, plots=False), spawn=s).run()
    agents = [m for name, m in s.peaks().items() if name.startswith("agent")]
    if rep["crashed"] or len(agents) != n:
        return {"policy": policy, "robots": n, "error": f"exit {code}, {len(agents)} agents sampled, crashed {rep['crashed'][:1]}"}
    stat = {k: {"mean": statistics.fmean(a[k] for a in agents), "max": max(a[k] for a in agents)} for k in ("pss", "rss", "uss")}
    return {"policy": policy, "robots": n, **stat, "world_pss": s.peaks()["world"]["pss"]}


def run_peer(scenario: str, steps: int) -> dict | None:
    try:
        from irsim_peer import run_irsim
    except ImportError as e:  # the bench extra is not installed
        return {"error": f"IR-SIM unavailable: {e}"}
    try:
        return run_irsim(scenario, steps)
    except Exception as e:  # noqa: BLE001 - a peer failure is reported in the table, not fatal
        return {"error": f"IR-SIM failed: {type(e).__name__}: {e}"}


def _fmt(x, nd=1):
    return "-" if x is None else f"{x:.{nd}f}"


def _median(runs: list[dict | None]) -> float | None:
    v = [r["steps_per_s"] for r in runs if r and r.get("steps_per_s")]
    return statistics.median(v) if v else None


def one_round(n: int, out: Path, a, reverse: bool) -> dict:
    """The fleet, then (replaying its commands) the world floor, the ray floor and IR-SIM; reversed every other round."""
    ls = run_ours(n, out, a.lockstep_s, realtime=False)
    sc = parse_scenario(yaml.safe_load(Path(ls["scenario"]).read_text()), ls["scenario"])
    cmds = _commands(out / f"lockstep-{n}")
    res = {"lockstep": ls}
    jobs = [("world_floor", lambda: world_floor(sc, cmds, a.endpoint)), ("ray_floor", lambda: ray_floor(sc, cmds)),
            ("irsim", lambda: None if a.no_peer else run_peer(ls["scenario"], a.peer_steps))]
    for name, job in (reversed(jobs) if reverse else jobs):
        res[name] = job()
    return res


def size_row(n: int, out: Path, a, t0: float) -> dict:
    rounds = []
    for r in range(a.rounds):
        rounds.append(one_round(n, out, a, reverse=r % 2 == 1))
        x = rounds[-1]
        print(f"[{time.time() - t0:6.0f} s] {n:2d} robots round {r + 1}: fleet {x['lockstep']['steps_per_s']:.1f}, world floor "
              f"{x['world_floor']['steps_per_s']:.1f}, ray floor {x['ray_floor']['steps_per_s']:.1f} steps/s", file=sys.stderr, flush=True)
    rt = run_ours(n, out, a.realtime_s, realtime=True) if a.realtime_s > 0 else None
    if rt is not None:
        print(f"[{time.time() - t0:6.0f} s] {n:2d} robots real time: x{rt['rtf']:.2f}, compute p99 {rt['compute_p99_ms']} ms, "
              f"state p99 {rt['state_p99_ms']} ms, sensor-to-command p99 {rt['loop_p99_ms']} ms", file=sys.stderr, flush=True)
    med = {k: _median([x[k] for x in rounds]) for k in ("lockstep", "world_floor", "ray_floor", "irsim")}
    ratio = {"fleet_over_world_floor": med["lockstep"] / med["world_floor"] if med["lockstep"] and med["world_floor"] else None,
             "fleet_over_irsim": med["lockstep"] / med["irsim"] if med["lockstep"] and med["irsim"] else None}
    return {"robots": n, "median_steps_per_s": med, "ratios": ratio, "rounds": rounds, "realtime": rt,
            "lockstep_loop_ms": [rounds[-1]["lockstep"]["loop_p50_ms"], rounds[-1]["lockstep"]["loop_p99_ms"]]}


def speed_table(rows: list[dict]) -> str:
    lines = ["| robots | fleet, lock-step steps/s | x real time | world floor steps/s | fleet / world floor (goal >= 0.6) "
             "| ray floor steps/s | IR-SIM steps/s | fleet / IR-SIM (goal >= 2) | real time: x real time, compute p99 (goal < 10) / state p99 (goal < 15) / sensor-to-command p99 [ms] |",
             "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in rows:
        m, q, rt = r["median_steps_per_s"], r["ratios"], r["realtime"] or {"rtf": None, "compute_p99_ms": None,
                                                                         "state_p99_ms": None, "loop_p99_ms": None}
        peer = r["rounds"][-1]["irsim"]
        ir = _fmt(m["irsim"]) if m["irsim"] else ("-" if not peer else peer.get("error", "-")[:40])
        lines.append(f"| {r['robots']} | {_fmt(m['lockstep'])} | {_fmt(m['lockstep'] and m['lockstep'] * 0.1)} | {_fmt(m['world_floor'])} "
                     f"| {_fmt(q['fleet_over_world_floor'], 2)} | {_fmt(m['ray_floor'])} | {ir} | {_fmt(q['fleet_over_irsim'], 2)} "
                     f"| x{_fmt(rt['rtf'], 2)}, {_fmt(rt['compute_p99_ms'], 1)} / {_fmt(rt['state_p99_ms'], 1)} "
                     f"/ {_fmt(rt['loop_p99_ms'], 1)} |")
    return "\n".join(lines)


def memory_table(mem: list[dict]) -> str:
    lines = ["| policy | robots | PSS per agent, mean / max [MB] | RSS, mean / max [MB] | USS, mean / max [MB] | goal (PSS) |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for m in mem:
        goal = 60 if m["policy"] == "pid" else 120
        if "error" in m:
            lines.append(f"| {m['policy']} | {m['robots']} | {m['error']} | | | < {goal} |")
            continue
        cell = [f"{m[k]['mean']:.1f} / {m[k]['max']:.1f}" for k in ("pss", "rss", "uss")]
        lines.append(f"| {m['policy']} | {m['robots']} | {cell[0]} | {cell[1]} | {cell[2]} | < {goal} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16, 32])
    ap.add_argument("--lockstep-s", type=float, default=30.0, help="sim seconds per lock-step run")
    ap.add_argument("--realtime-s", type=float, default=15.0, help="sim (= wall) seconds per real-time run (0: none)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds of fleet, floors and IR-SIM per size")
    ap.add_argument("--peer-steps", type=int, default=300, help="IR-SIM steps per run")
    ap.add_argument("--no-peer", action="store_true", help="skip IR-SIM")
    ap.add_argument("--memory-size", type=int, default=8, help="robots in the memory runs (0: none)")
    ap.add_argument("--memory-s", type=float, default=10.0, help="sim seconds per memory run")
    ap.add_argument("--tiny", action="store_true", help="4 robots, 3 sim-s, 1 round, 30 IR-SIM steps: that it works")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "fleet-bench")
    ap.add_argument("--compare", type=Path, metavar="OLD.json", help="print this run's medians against an earlier "
                    "run's fleet_bench.json (new / old per size and column)")
    a = ap.parse_args(argv)
    if a.tiny:
        a.sizes, a.lockstep_s, a.realtime_s, a.rounds, a.peer_steps, a.memory_size, a.memory_s = [4], 3.0, 2.0, 1, 30, 4, 3.0
    sigterm_as_interrupt()
    a.out.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(Path(__file__).parent))
    from stack.comm.session import free_tcp_endpoint

    a.endpoint = free_tcp_endpoint()
    router = Proc("router", [sys.executable, "-m", "stack.comm.router", "--listen", a.endpoint], a.out / "floor-router.log",
                  dict(os.environ))
    t0 = time.time()
    try:
        from stack.fleet.procs import wait_port

        wait_port(a.endpoint, process=router)
        rows = [size_row(n, a.out, a, t0) for n in a.sizes]
    finally:
        router.stop(5)
        router.close()
    mem = [memory(a.memory_size, pol, a.out, a.memory_s) for pol in ("pid", "drl")] if a.memory_size else []
    text = speed_table(rows) + ("\n\n" + memory_table(mem) if mem else "")
    print(text)
    (a.out / "fleet_bench.md").write_text(text + "\n")
    (a.out / "fleet_bench.json").write_text(json.dumps({"sizes": rows, "memory": mem}, indent=2))
    print(f"\nwritten: {a.out / 'fleet_bench.md'}, {a.out / 'fleet_bench.json'}", file=sys.stderr)
    if a.compare is not None:
        print("\n" + compare_table(json.loads(a.compare.read_text())["sizes"], rows, a.compare))
    return 0


def compare_table(old: list[dict], new: list[dict], old_path: Path) -> str:
    """New / old of each size's median steps/s (fleet, floors, IR-SIM) and of the fleet's ratio to its world floor,
    for the sizes both runs have: a slower fleet shows as a ratio under 1."""
    cols = ("lockstep", "world_floor", "ray_floor", "irsim")
    before = {r["robots"]: r for r in old}
    lines = [f"against {old_path}: new / old", "| robots | fleet | world floor | ray floor | IR-SIM | fleet / world floor, old -> new |",
             "| ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in new:
        o = before.get(r["robots"])
        if o is None:
            continue
        m, mo = r["median_steps_per_s"], o["median_steps_per_s"]
        cells = [_fmt(m[c] / mo[c], 2) if m.get(c) and mo.get(c) else "-" for c in cols]
        fo, fn = o["ratios"]["fleet_over_world_floor"], r["ratios"]["fleet_over_world_floor"]
        lines.append(f"| {r['robots']} | " + " | ".join(cells) + f" | {_fmt(fo, 2)} -> {_fmt(fn, 2)} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
