"""Immune-network policy (``--policy aina``) cost per control step.

Times ``ImmuneNetwork.step`` (eq. (4)-(10) integration + Algorithm 1) and the whole
``AinaPolicy.act`` (sector sensors from a 180-beam scan, network, eq. (13)) with
``time.perf_counter`` over a stream of changing scans; prints p50 / p99 / max in
microseconds for a few antibody counts. Goal (issue 6): < 1 ms per step.

    python bench/aina_bench.py
    python bench/aina_bench.py --steps 5000 --n-ab 36 72
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stack.policies import Observation, make_policy  # noqa: E402
from stack.scenario import load_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _stream(steps: int, rng: np.random.Generator):
    ang = np.linspace(-math.pi / 2, math.pi / 2, 180)
    for k in range(steps):
        r = np.full(180, 5.0)
        c = math.sin(0.01 * k)  # an obstacle sweeping across the field of view
        r[np.abs(ang - c) < 0.2] = 1.5 + 0.5 * math.cos(0.03 * k)
        r += rng.normal(0, 0.01, 180)
        yield Observation(d_g=2.0 + math.sin(0.02 * k), alpha_g=0.3 * math.sin(0.05 * k), v=0.5, w=0.0,
                          neighbours=np.array([[3.0, 1.0]]), scans=r[None, :], goal_velocity=(0.5, 0.0),
                          yaw=0.1 * k % (2 * math.pi), dt=0.1, target_yaw=0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--n-ab", type=int, nargs="+", default=[18, 36, 72])
    a = ap.parse_args()
    base = load_scenario(ROOT / "scenarios" / "four-robot-obstacles.yaml").robot(1)
    print(f"| N_Ab | network step p50 / p99 [us] | act p50 / p99 / max [us] |")
    print("| --- | --- | --- |")
    for n_ab in a.n_ab:
        robot = base.with_config("aina", replace(base.config_for("aina"), n_ab=n_ab))
        pol = make_policy("aina", robot, seed=0)
        rng = np.random.default_rng(0)
        act, net = [], []
        for obs in _stream(a.steps, rng):
            t0 = time.perf_counter()
            pol.act(obs)
            act.append(time.perf_counter() - t0)
            ag = pol.antigen(obs)
            t0 = time.perf_counter()
            pol.net.step(ag)
            net.append(time.perf_counter() - t0)
        act_us, net_us = np.array(act[100:]) * 1e6, np.array(net[100:]) * 1e6
        print(f"| {n_ab} | {np.percentile(net_us, 50):.0f} / {np.percentile(net_us, 99):.0f} | "
              f"{np.percentile(act_us, 50):.0f} / {np.percentile(act_us, 99):.0f} / {act_us.max():.0f} |")


if __name__ == "__main__":
    main()
