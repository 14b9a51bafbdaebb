"""Goal error and estimate error against device settings, ideal vs hardware-like simulated devices (issue 16).

One leader drives 6 m to its formation goal from a boot pose away from the site origin, in real time
(``--realtime``) or lock-step, on each driver's simulated device; each row is one run: the device's setting, the
leader's final distance to the goal and its estimator RMSE, from the fleet's report.

    python bench/hardware_bench.py --out runs/hardware-bench [--small] [--lockstep]

Sweeps: Jackal lidar rate (5, 10, 15, 25, 40 Hz), Jackal odometry rate (10, 25, 50 Hz), Jackal clock offset
(0, 3.7, -2 s), ideal vs hardware-like for jackal, can and mavlink. ``--small``: lidar 5/15/40 Hz, one offset, and
the ideal/hardware-like pairs. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import yaml

BOOT = (2.0, -1.0, 30.0)
DRIVE_M = 6.0


def scenario(driver: str, device: dict, ideal: bool) -> dict:
    x, y, yaw = BOOT
    goal = [x + DRIVE_M * math.cos(math.radians(yaw)), y + DRIVE_M * math.sin(math.radians(yaw))]
    return {"name": "hardware-bench", "seed": 3, "dt": 0.1, "duration": 20.0,
            "world": {"obstacles": []},
            "robot": {"radius": 0.5, "v_max": 1.0, "w_max": 1.0, "comm_range": 10.0,
                      "lidar": {"beams": 180, "fov_deg": 180, "range": 5.0, "noise_std": 0.0},
                      "device": {"ideal": ideal} | ({driver: device} if device else {})},
            "comm": {"loss": 0.0, "latency_ms": 0},
            "site": {"datum": [47.397742, 8.545594, 488.0]},
            "formation": {"leader": 0, "goal": goal, "slots": {}},
            "robots": [{"id": 0, "role": "leader", "pose": list(BOOT), "driver": driver}],
            "success": {"goal_tolerance": 0.5, "max_time": 20.0, "no_collisions": True}}


def cases(small: bool):
    """(driver, swept setting in words, device settings, ideal)."""
    rates = (5, 15, 40) if small else (5, 10, 15, 25, 40)
    for hz in rates:
        yield "jackal", f"lidar {hz} Hz", {"lidar_rate_hz": float(hz)}, False
    for hz in (() if small else (10, 25, 50)):
        yield "jackal", f"odometry {hz} Hz", {"odom_rate_hz": float(hz)}, False
    for off in ((3.7,) if small else (0.0, 3.7, -2.0)):
        yield "jackal", f"clock {off:+g} s", {"clock_offset_s": off}, False
    for driver in ("jackal", "can", "mavlink"):
        for ideal in (True, False):
            yield driver, "ideal" if ideal else "hardware-like", {}, ideal


def run(out: Path, driver: str, device: dict, ideal: bool, realtime: bool) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    path = out / "scenario.yaml"
    path.write_text(yaml.safe_dump(scenario(driver, device, ideal)))
    cmd = [sys.executable, "-m", "stack.fleet", "run", str(path), "--out", str(out / "run"), "--no-plots", "--no-progress", "--no-record"]
    proc = subprocess.run(cmd + (["--realtime"] if realtime else []), capture_output=True, text=True, timeout=300)
    rep_path = out / "run" / "report.json"
    if not rep_path.exists():
        return {"error": (proc.stderr.strip().splitlines() or ["no report"])[-1]}
    rep = json.loads(rep_path.read_text())
    r = rep["robots"]["0"]
    return {"success": rep["success"], "goal_m": r["final_error_m"], "estimate_m": r["estimator_rmse_m"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("runs/hardware-bench"))
    ap.add_argument("--small", action="store_true", help="fewer settings (a quick look)")
    ap.add_argument("--lockstep", action="store_true", help="lock-step instead of real time")
    a = ap.parse_args(argv)
    rows = ["| driver | setting | success | goal error [m] | estimate RMSE [m] |", "| --- | --- | --- | --- | --- |"]
    for i, (driver, words, device, ideal) in enumerate(cases(a.small)):
        res = run(a.out / f"{i:02d}-{driver}", driver, device, ideal, not a.lockstep)
        if "error" in res:
            rows.append(f"| {driver} | {words} | error: {res['error']} | | |")
        else:
            rows.append(f"| {driver} | {words} | {res['success']} | {res['goal_m']} | {res['estimate_m']} |")
        print(rows[-1], file=sys.stderr, flush=True)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
