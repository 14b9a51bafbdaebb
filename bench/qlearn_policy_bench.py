"""``--policy qlearn`` cost: time per replan and per control step (issue 8, the online part).

Drives the policy closed-loop in a small numpy world (a unicycle, a 180-beam 180-degree 5 m lidar
ray-cast against circles; no pybullet, no Zenoh) laid out like ``four-robot-obstacles.yaml``
(its cylinders, and each box as the circle around it), and times with ``time.perf_counter``:

* the leader: every Q-L5 replan (``policy.plan_times``: grid inflation, reachability, ``plan``,
  string pulling), and ``act`` on steps without a replan (p50 / p99 / max) and with one;
* a follower tracking a slot 3 m behind-left of a scripted leader (eq. (12)-(13) over the
  candidates, plus the grid update);
* ``plan`` itself, cold and warm-started, on the leader's final grid.

    python bench/qlearn_policy_bench.py
    python bench/qlearn_policy_bench.py --cell 0.25 --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stack.planning.qlearning import QLearningConfig, plan  # noqa: E402
from stack.train.drlworld import ray_cast  # noqa: E402
from stack.policies.base import Observation  # noqa: E402
from stack.policies.qlearn import QlearnPolicy, QlearnPolicyConfig  # noqa: E402
from stack.scenario import load_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BEAMS, FOV, RANGE = 180, math.pi, 5.0
REL = np.linspace(-FOV / 2, FOV / 2, BEAMS)


def circles_of(scenario: Path) -> list[tuple[float, float, float]]:
    out = []
    for o in load_scenario(scenario).obstacles:
        kind = getattr(o, "type", getattr(o, "kind", ""))
        if kind == "cylinder":
            out.append((o.x, o.y, o.radius))
        elif kind == "box":
            out.append((o.x, o.y, 0.5 * math.hypot(o.size_x, o.size_y)))
    return out


def raycast(x: float, y: float, yaw: float, circles) -> np.ndarray:
    """Ranges of a 180-beam, 180-degree, 5 m lidar at (x, y, yaw) against circles (cx, cy, R)."""
    c = np.asarray(circles, float).reshape(-1, 3)
    return ray_cast(np.float64(x), np.float64(y), np.float64(yaw), c, np.zeros((0, 5)), REL, 0.0, RANGE)


def observe(x, y, yaw, target, scan, neighbours=(), gv=(0.0, 0.0)) -> Observation:
    nb = np.array([(math.hypot(a - x, b - y), math.atan2(b - y, a - x) - yaw) for a, b in neighbours])
    nb = nb.reshape(-1, 2)
    dx, dy = target[0] - x, target[1] - y
    return Observation(d_g=math.hypot(dx, dy), alpha_g=math.atan2(dy, dx) - yaw, v=0.0, w=0.0, neighbours=nb, scans=scan[None, :], goal_velocity=gv, yaw=yaw, scan_range=RANGE,
                       dt=0.1, x=x, y=y, target=target)


def q(a, p) -> float:
    return float(np.percentile(a, p)) * 1e3 if len(a) else float("nan")


def run_leader(cfg: QlearnPolicyConfig, circles, seed: int, goal=(38.0, 0.0), steps: int = 1500):
    pol = QlearnPolicy(cfg, role="leader", radius=0.5, v_max=1.0, w_max=1.0, lidar_fov=FOV, lidar_range=RANGE,
                       lidar_noise=0.01, seed=seed)
    rng = np.random.default_rng(seed)
    x, y, yaw = 0.0, 0.0, 0.0
    plain, with_plan = [], []
    clearance = math.inf
    for _ in range(steps):
        scan = np.clip(raycast(x, y, yaw, circles) + rng.normal(0, 0.01, BEAMS), 0, RANGE)
        n = len(pol.plan_times)
        t0 = time.perf_counter()
        v, w = pol.act(observe(x, y, yaw, goal, scan))
        (with_plan if len(pol.plan_times) > n else plain).append(time.perf_counter() - t0)
        x, y, yaw = x + v * math.cos(yaw) * 0.1, y + v * math.sin(yaw) * 0.1, yaw + w * 0.1
        clearance = min(clearance, min(math.hypot(x - cx, y - cy) - R for cx, cy, R in circles))
        if math.hypot(goal[0] - x, goal[1] - y) < cfg.arrive + 0.05 and v == 0.0:
            break
    return pol, plain, with_plan, math.hypot(goal[0] - x, goal[1] - y), clearance


def run_follower(cfg: QlearnPolicyConfig, circles, steps: int = 700):
    pol = QlearnPolicy(cfg, role="follower", radius=0.5, v_max=1.0, w_max=1.0, lidar_fov=FOV, lidar_range=RANGE)
    lx, ly = 0.0, 0.0
    fx, fy, fyaw = -2.1, 2.1, 0.0
    times = []
    for _ in range(steps):
        slot = (lx - 2.1, ly + 2.1)
        scan = raycast(fx, fy, fyaw, circles + [(lx, ly, 0.5)])
        t0 = time.perf_counter()
        v, w = pol.act(observe(fx, fy, fyaw, slot, scan, neighbours=[(lx, ly)], gv=(0.5, 0.0)))
        times.append(time.perf_counter() - t0)
        fx, fy, fyaw = fx + v * math.cos(fyaw) * 0.1, fy + v * math.sin(fyaw) * 0.1, fyaw + w * 0.1
        lx += 0.05
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=str(ROOT / "scenarios" / "four-robot-obstacles.yaml"))
    ap.add_argument("--cell", type=float, default=QlearnPolicyConfig.cell)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    a = ap.parse_args()
    cfg = QlearnPolicyConfig(cell=a.cell)
    circles = circles_of(Path(a.scenario))
    print(f"leader: 0,0 -> 38,0 past {len(circles)} obstacles, cell {cfg.cell} m\n")
    print("| seed | grid | plans (warm) | replan p50 / max [ms] | act p50 / p99 / max [ms] (no replan) "
          "| act with replan max [ms] | end error [m] | min clearance [m] |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    last = None
    for seed in a.seeds:
        pol, plain, with_plan, err, clr = run_leader(cfg, circles, seed)
        c = pol.counters
        print(f"| {seed} | {pol.grid.shape[0]} x {pol.grid.shape[1]} | {c['plans']} ({c['warm_plans']}) "
              f"| {q(pol.plan_times, 50):.1f} / {max(pol.plan_times) * 1e3:.1f} "
              f"| {q(plain, 50):.2f} / {q(plain, 99):.2f} / {max(plain) * 1e3:.2f} "
              f"| {max(with_plan, default=0) * 1e3:.1f} "
              f"| {err:.2f} | {clr:.2f} |")
        last = pol
    reasons = {k: v for k, v in last.counters.items() if v}
    print(f"\ncounters (seed {a.seeds[-1]}): {reasons}")

    ft = run_follower(cfg, circles)
    print(f"\nfollower act p50 / p99 / max [ms]: {q(ft, 50):.2f} / {q(ft, 99):.2f} / {max(ft) * 1e3:.2f}")

    # plan() alone on the final grid, cold and warm (the warm start after one new obstacle cell)
    g = last.grid
    blocked = g.blocked(0.5)
    s, goal = g.cell_of(0.0, 0.0), g.cell_of(38.0, 0.0)
    if blocked[s] or blocked[goal]:
        return
    qc = QLearningConfig(variant="Q-L5", seed=0, fill_guard=True, max_rounds=cfg.max_rounds,
                         max_steps=4 * (abs(s[0] - goal[0]) + abs(s[1] - goal[1])) + 50)
    t0 = time.perf_counter()
    cold = plan(blocked, s, goal, qc)
    t_cold = time.perf_counter() - t0
    b2 = blocked.copy()
    b2[(s[0] + goal[0]) // 2, s[1] + 6] = True
    t0 = time.perf_counter()
    warm = plan(b2, s, goal, qc, warm_start=cold)
    t_warm = time.perf_counter() - t0
    print(f"plan() on the final {blocked.shape[0]} x {blocked.shape[1]} grid: cold {t_cold * 1e3:.1f} ms "
          f"({cold.rounds} rounds, converged {cold.converged}), warm {t_warm * 1e3:.1f} ms ({warm.rounds} rounds, "
          f"converged {warm.converged})")


if __name__ == "__main__":
    main()
