"""Pose EKF benchmark: cost per step, and position RMSE against odometry noise.

(a) Microseconds per period of ``update_odometry + update_gyro + predict`` (the per-period work
    of an agent; see the call order in ``stack/estimation/ekf.py``) and per ``update_fix``,
    timed with ``time.perf_counter`` over a simulated sensor stream (best of three repeats).
(b) A markdown table of position RMSE [m] over 5-minute simulated runs (dt = 0.1 s, several
    seeds averaged) for wheel-odometry noise v_std = w_std in {0, 0.02, 0.05, 0.1}, with
    odometry only, odometry + gyro, odometry + 1 Hz fixes (0.3 m) and all three. The filter is
    told the true noise (floored by ``EkfConfig``: 0.02 for the odometry) and starts on the true
    pose, so the table shows what the sensors cost, not an initial-heading error.

The trajectories are the ones the tests check: ``simulate`` and ``run_filter`` come from
``tests/test_estimation.py`` (a unicycle on smooth random commands, integrated on a finer grid).

    python bench/estimator_bench.py
    python bench/estimator_bench.py --seeds 10 --minutes 5 --steps 20000
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stack.estimation.ekf import PoseEKF  # noqa: E402
from tests.test_estimation import pos_err, run_filter, simulate  # noqa: E402

DT = 0.1
GYRO_STD = 0.02
FIX_STD = 0.3
NOISE_LEVELS = (0.0, 0.02, 0.05, 0.1)


def time_steps(steps: int, repeats: int = 3) -> tuple[float, float]:
    """Best-of-``repeats`` microseconds per (odometry + gyro + predict) period and per fix."""
    run = simulate(0, steps, v_std=0.05, w_std=0.05, gyro_std=GYRO_STD, fix_std=FIX_STD, fix_every=1)
    odo, gyro, fix = run.odom.tolist(), run.gyro.tolist(), run.fix.tolist()
    best_step = best_fix = math.inf
    for _ in range(repeats):
        f = PoseEKF(*run.start)
        t0 = time.perf_counter()
        for k in range(steps):
            f.update_odometry(odo[k][0], odo[k][1], 0.05, 0.05)
            f.update_gyro(gyro[k], GYRO_STD)
            f.predict(DT)
        best_step = min(best_step, (time.perf_counter() - t0) / steps)
        # fixes on a second pass of the same stream, timed call by call
        f = PoseEKF(*run.start)
        t_fix, accepted = 0.0, 0
        for k in range(steps):
            f.update_odometry(odo[k][0], odo[k][1], 0.05, 0.05)
            f.update_gyro(gyro[k], GYRO_STD)
            f.predict(DT)
            t0 = time.perf_counter()
            accepted += f.update_fix(fix[k][0], fix[k][1], FIX_STD)
            t_fix += time.perf_counter() - t0
        best_fix = min(best_fix, t_fix / steps)
    print(f"fixes accepted in the timing run: {accepted}/{steps}")
    return best_step * 1e6, best_fix * 1e6


def rmse_table(seeds: int, minutes: float) -> list[list[float]]:
    """Rows per noise level: position RMSE averaged over seeds for the four sensor sets."""
    n = int(round(minutes * 60 / DT))
    sets = [(None, None), (GYRO_STD, None), (None, FIX_STD), (GYRO_STD, FIX_STD)]  # (gyro, fix)
    rows = []
    for s_odo in NOISE_LEVELS:
        row = []
        for g, fx in sets:
            rm = []
            for seed in range(seeds):
                run = simulate(seed, n, v_std=s_odo, w_std=s_odo, gyro_std=g, fix_std=fx)
                est, _, _ = run_filter(run, v_std=s_odo, w_std=s_odo, gyro_std=GYRO_STD, fix_std=FIX_STD,
                                       seed=seed, exact_start=True)
                rm.append(math.sqrt(np.mean(pos_err(est, run.truth) ** 2)))
            row.append(float(np.mean(rm)))
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=20000, help="periods timed (default %(default)s)")
    ap.add_argument("--seeds", type=int, default=5, help="seeds averaged per table cell (default %(default)s)")
    ap.add_argument("--minutes", type=float, default=5.0, help="simulated minutes per run (default %(default)s)")
    a = ap.parse_args(argv)

    step_us, fix_us = time_steps(a.steps)
    print(f"\n## Cost per call ({a.steps} periods, best of 3, Python {sys.version.split()[0]})\n")
    print("| work | us |\n|---|---:|")
    print(f"| update_odometry + update_gyro + predict (one period) | {step_us:.1f} |")
    print(f"| update_fix (gate included) | {fix_us:.1f} |")

    t0 = time.perf_counter()
    rows = rmse_table(a.seeds, a.minutes)
    print(f"\n## Position RMSE [m], {a.minutes:g}-minute runs, mean of {a.seeds} seeds "
          f"(gyro {GYRO_STD} rad/s, fixes {FIX_STD} m at 1 Hz, exact start)\n")
    print("| odometry v_std = w_std | odometry only | odometry + gyro | odometry + 1 Hz fixes | odometry + gyro + 1 Hz fixes |")
    print("|---:|---:|---:|---:|---:|")
    for s_odo, row in zip(NOISE_LEVELS, rows):
        print(f"| {s_odo:g} | " + " | ".join(f"{r:.3f}" for r in row) + " |")
    print(f"\n(table: {time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
