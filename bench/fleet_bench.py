"""Fleet benchmark: real-time factor, control-loop and Zenoh state latency for 4-32 robots.

For each fleet size it runs our whole multi-process fleet (router + world + one agent
process per robot, PID, dt = 0.1 s) in lock-step and in real time, and beside it the
single-process IR-SIM peer simulator doing the same world work (``bench/irsim_peer.py``;
``pip install -e '.[bench]'``). Prints one markdown table and writes it with the raw
numbers to ``--out``.

    python bench/fleet_bench.py                       # 4, 8, 16, 32 robots
    python bench/fleet_bench.py --sizes 4 32 --lockstep-s 30 --realtime-s 20
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stack.fleet.orchestrator import FleetConfig, run_fleet, sigterm_as_interrupt  # noqa: E402
from stack.scenario import parse_scenario  # noqa: E402


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
            "state_p50_ms": rep["state_latency_ms"]["p50"], "state_p99_ms": rep["state_latency_ms"]["p99"],
            "late_steps": world.get("late_steps"), "scenario": str(path)}


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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16, 32])
    ap.add_argument("--lockstep-s", type=float, default=30.0, help="sim seconds per lock-step run")
    ap.add_argument("--realtime-s", type=float, default=15.0, help="sim (= wall) seconds per real-time run")
    ap.add_argument("--peer-steps", type=int, default=300, help="IR-SIM steps per run")
    ap.add_argument("--no-peer", action="store_true", help="skip IR-SIM")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "fleet-bench")
    a = ap.parse_args(argv)
    sigterm_as_interrupt()
    a.out.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(Path(__file__).parent))
    rows = []
    t0 = time.time()
    for n in a.sizes:
        ls = run_ours(n, a.out, a.lockstep_s, realtime=False)
        print(f"[{time.time() - t0:6.0f} s] {n:2d} robots lock-step: {ls['steps_per_s']:.1f} steps/s", file=sys.stderr, flush=True)
        rt = run_ours(n, a.out, a.realtime_s, realtime=True)
        print(f"[{time.time() - t0:6.0f} s] {n:2d} robots real time: x{rt['rtf']:.2f}, loop p99 {rt['loop_p99_ms']} ms", file=sys.stderr, flush=True)
        peer = None if a.no_peer else run_peer(ls["scenario"], a.peer_steps)
        rows.append({"robots": n, "lockstep": ls, "realtime": rt, "irsim": peer})
    lines = [
        "| robots | lock-step steps/s | lock-step x real time | loop p50 / p99 [ms] (lock-step) | real time: x real time | loop p50 / p99 [ms] (real time) | state latency p50 / p99 [ms] (real time) | IR-SIM steps/s (1 process) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        ls, rt, peer = r["lockstep"], r["realtime"], r["irsim"]
        ps = "-" if not peer else (f"{peer['steps_per_s']:.1f}" if "steps_per_s" in peer else peer["error"][:40])
        lines.append(f"| {r['robots']} | {_fmt(ls['steps_per_s'])} | {_fmt(ls['rtf'])} | {_fmt(ls['loop_p50_ms'], 2)} / {_fmt(ls['loop_p99_ms'], 2)} "
                     f"| {_fmt(rt['rtf'], 2)} | {_fmt(rt['loop_p50_ms'], 2)} / {_fmt(rt['loop_p99_ms'], 2)} "
                     f"| {_fmt(rt['state_p50_ms'], 2)} / {_fmt(rt['state_p99_ms'], 2)} | {ps} |")
    table = "\n".join(lines)
    print(table)
    (a.out / "fleet_bench.md").write_text(table + "\n")
    (a.out / "fleet_bench.json").write_text(json.dumps(rows, indent=2))
    print(f"\nwritten: {a.out / 'fleet_bench.md'}, {a.out / 'fleet_bench.json'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
