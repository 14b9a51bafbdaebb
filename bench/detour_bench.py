"""The planned detour's cost (``stack/agents/detour.py``): how long one plan takes in an agent's step.

A walled corridor (40 m x 14 m) with a cross wall whose 2.6 m gap lies off the line, seen by a robot that has
looked along it (the memory filled from analytic ray casts as the robot drives the corridor), then
``DetourPlanner.plan`` from the robot pressed against the cross wall to a goal 20 m beyond it, ``--repeat``
times; prints p50 / p99 / max in milliseconds and the memory's and the window's size. A plan runs only while a
robot is stuck, once per ``replan_s`` (1 s).

    python bench/detour_bench.py
    python bench/detour_bench.py --resolution 0.2 --repeat 50
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stack.agents.detour import DetourConfig, DetourPlanner, ScanMemory  # noqa: E402
from stack.train.drlworld import ray_cast  # noqa: E402

# [cx, cy, hx, hy, yaw]: the corridor's walls at y = +-7, a cross wall at x = 12 with its gap at y 3.4..6.0
BOXES = np.array([[15.0, 7.0, 25.0, 0.1, 0.0], [15.0, -7.0, 25.0, 0.1, 0.0],
                  [12.0, -1.8, 0.15, 5.2, 0.0], [12.0, 6.5, 0.15, 0.5, 0.0]])
CIRCLES = np.array([[6.0, -3.0, 0.5], [8.0, 2.5, 0.45]])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", type=float, default=DetourConfig.resolution)
    ap.add_argument("--repeat", type=int, default=30)
    a = ap.parse_args(argv)
    if a.resolution <= 0 or a.repeat < 1:
        ap.error("--resolution must be > 0 and --repeat >= 1")
    cfg = DetourConfig(resolution=a.resolution)
    mem = ScanMemory(cfg.resolution, cfg.max_cells)
    beams = np.linspace(-math.pi / 2, math.pi / 2, 180)
    for x in np.arange(0.0, 11.2, 0.05):  # the robot drives up to the cross wall, looking ahead and about
        for yaw in (0.0, 0.8, -0.8):
            s = ray_cast(np.array(x), np.array(0.0), np.array(yaw), CIRCLES, BOXES, beams, 0.51, 5.0)
            mem.add(float(x), 0.0, yaw, s, math.pi, 5.0)
    planner = DetourPlanner(cfg, mem, 0.5)
    me, goal = (11.2, 0.0), (32.0, 0.0)
    times = []
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        ok = planner.plan(0.0, me, goal)
        times.append((time.perf_counter() - t0) * 1e3)
    if not ok:
        print("no path found (a defect: the gap is there)", file=sys.stderr)
        return 1
    blocked = planner.grid[0]
    p = np.percentile(times, [50, 99])
    print(f"plan: p50 {p[0]:.1f} ms, p99 {p[1]:.1f} ms, max {max(times):.1f} ms over {a.repeat} plans; "
          f"memory {len(mem.cells)} cells of {cfg.resolution:g} m, window {blocked.shape[0]} x {blocked.shape[1]} cells, "
          f"path {len(planner.path)} points, first waypoint {tuple(round(v, 2) for v in planner.waypoint(me))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
