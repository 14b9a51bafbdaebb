"""Chang 2020 Tables 2-3 beside ours: arrival spread and time to complete, fuzzy / LSTM / no MRC.

  python bench/chang_table.py --seeds 10 --loss 0,0.1,0.3 --out runs/chang-table            # the fleet
  python bench/chang_table.py --backend numpy --seeds 10 --out runs/chang-table-numpy        # the numpy world

Backends:
- ``fleet`` (default): one ``stack-fleet run SCENARIO --policy fuzzy|fuzzy-lstm --seed S --loss X``
  process per run, ``--jobs N`` at a time or on Dask (``--engine dask``, ``stack.fleet.jobs``)
  (router, pybullet world, one agent per robot, EKF on noisy odometry + fixes,
  lidar noise from the scenario). "No MRC" is ``--policy fuzzy`` on a copy of the scenario with
  ``robot.fuzzy.coordinator: none``.
- ``numpy``: :mod:`stack.train.fuzzyworld` (exact pose, lidar noise, per-message loss): 100x faster,
  no estimator, no driver dynamics.

Per scenario x coordinator x loss: mean +- std over the seeds of ``arrival_spread_steps`` and of the
time to complete (last arrival / dt), runs where every robot arrived, and total collisions.
Writes OUT/chang_table.md and OUT/chang_table.json; prints the markdown.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetrun import engine, report_of, scenario_with, setting  # noqa: E402  (bench/, beside this script)

from stack.fleet.jobs import Job, add_engine_args, cli_task, run_jobs  # noqa: E402

PAPER = {  # (spread, completion) in steps, Tables 2 and 3
    "chang-three": {"flc": (5, 785), "lstm": (8, 778), "none": (504, 901)},
    "chang-six": {"flc": (58, 965), "lstm": (34, 907), "none": (839, 901)},
}
LABEL = {"flc": "fuzzy MRC", "lstm": "LSTM MRC", "none": "no MRC"}


def _csv(kind):
    return lambda s: [kind(x) for x in s.split(",") if x]


def fleet_job(scenario: Path, coord: str, seed: int, loss: float, out: Path, fuzzy: dict | None = None) -> Job:
    """One ``stack-fleet run`` of this coordinator; "no MRC" is ``--policy fuzzy`` on a copy of the scenario with
    ``robot.fuzzy.coordinator: none``."""
    policy = "fuzzy-lstm" if coord == "lstm" else "fuzzy"
    over = dict(fuzzy or {}) | ({"coordinator": "none"} if coord == "none" else {})
    path = scenario_with(scenario, "fuzzy", over, out, coord)
    return Job(cli_task, (str(path), str(out), ("--policy", policy, "--seed", str(seed), "--loss", str(loss))),
               f"{scenario.stem} {coord} loss {loss:g} seed {seed}")


def fleet_row(result) -> dict:
    """A fleet run's row: arrival spread, time to complete, collisions, closest approaches."""
    rep, err, wall = report_of(result)
    if rep is None:
        return {"error": [err], "wall_s": wall}
    arr = [r.get("arrival_time_s") for r in rep["robots"].values()]
    dt = rep.get("dt", 0.1)
    complete = None if any(a is None for a in arr) else round(max(arr) / dt)
    col = rep["collisions"]["robot_robot"] + rep["collisions"]["robot_obstacle"]
    return {"spread": rep.get("arrival_spread_steps"), "complete": complete, "collisions": col,
            "min_obstacle_m": rep.get("min_obstacle_distance_m"), "min_robot_m": rep.get("min_robot_distance_m"),
            "wall_s": round(wall, 1)}


def numpy_run(scenario: Path, coord: str, seed: int, loss: float, fuzzy: dict | None = None) -> dict:
    from stack.policies.fuzzy import make_fuzzy
    from stack.scenario import load_scenario
    from stack.train.fuzzyworld import RobotSpec, SimConfig, World, run

    sc = load_scenario(scenario)
    r0 = sc.robots[0]
    cfg = SimConfig(dt=sc.dt, radius=r0.radius, v_max=r0.v_max, w_max=r0.w_max, beams=r0.lidar.beams, fov=r0.lidar.fov,
                    range_max=r0.lidar.range, noise_std=r0.lidar.noise_std, comm_range=r0.comm_range, loss=loss,
                    goal_tol=sc.success.goal_tolerance, max_steps=int(round(sc.duration / sc.dt)))
    t0 = time.perf_counter()
    res = run(World.from_scenario(sc), [RobotSpec(r.pose, r.goal) for r in sc.robots],
              [make_fuzzy(_with_fuzzy(r, fuzzy), coordinator=coord) for r in sc.robots], cfg, seed=seed)
    return {"spread": res.spread, "complete": res.complete, "collisions": res.collisions_robot + res.collisions_obstacle,
            "min_obstacle_m": round(res.min_obstacle, 3), "min_robot_m": round(res.min_robot, 3),
            "wall_s": round(time.perf_counter() - t0, 1)}


def _with_fuzzy(robot, fuzzy: dict | None):
    """The robot with these ``robot.fuzzy`` settings over its own (checked by ``main``)."""
    if not fuzzy:
        return robot
    from stack.policies.fuzzy import FuzzyConfig
    from stack.settings import read

    return robot.with_config("fuzzy", read(FuzzyConfig, fuzzy, "robot.fuzzy", robot.config_for("fuzzy")))


def _ms(xs):
    xs = [x for x in xs if x is not None]
    if not xs:
        return "-"
    return f"{np.mean(xs):.1f} +- {np.std(xs):.1f}, median {np.median(xs):g}"


def table(results: dict, seeds: int, backend: str) -> str:
    lines = [f"backend: {backend}; {seeds} seed(s) per row; steps of 0.1 s; paper in brackets", "",
             "| scenario | coordinator | loss | spread [steps] | time to complete [steps] | all arrived | collisions | min obstacle / robot [m] |",
             "| --- | --- | ---: | --- | --- | ---: | ---: | --- |"]
    for key, runs in results.items():
        scen, coord, loss = key.split("|")
        ps, pc = PAPER.get(scen, {}).get(coord, (None, None))
        ok = sum(1 for r in runs if r.get("complete") is not None)
        cols = sum(r.get("collisions", 0) or 0 for r in runs)
        mo = min((r["min_obstacle_m"] for r in runs if r.get("min_obstacle_m") is not None), default=None)
        mr = min((r["min_robot_m"] for r in runs if r.get("min_robot_m") is not None), default=None)
        errs = [r for r in runs if "error" in r]
        lines.append(f"| {scen} | {LABEL[coord]} | {float(loss):.0%} | {_ms([r.get('spread') for r in runs])} ({ps}) | "
                     f"{_ms([r.get('complete') for r in runs])} ({pc}) | {ok}/{len(runs)} | {cols} | "
                     f"{mo if mo is None else round(mo, 2)} / {mr if mr is None else round(mr, 2)}"
                     f"{' (' + str(len(errs)) + ' errors)' if errs else ''} |")
    return "\n".join(lines)


def _by_key(plan: list, rows: dict[int, dict]) -> dict[str, list]:
    """The rows finished so far (index into ``plan``) under their ``scenario|coordinator|loss`` keys."""
    out: dict[str, list] = {}
    for j in sorted(rows):
        (name, _, coord, loss), seed = plan[j]
        out.setdefault(f"{name}|{coord}|{loss}", []).append(rows[j] | {"seed": seed})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", choices=("fleet", "numpy"), default="fleet")
    ap.add_argument("--scenarios", type=_csv(str), default=["scenarios/chang-three.yaml", "scenarios/chang-six.yaml"])
    ap.add_argument("--coordinators", type=_csv(str), default=["flc", "lstm", "none"])
    ap.add_argument("--loss", type=_csv(float), default=[0.0, 0.1, 0.3])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--out", type=Path, default=Path("runs/chang-table"))
    ap.add_argument("--fuzzy", type=setting("--fuzzy", "fuzzy"), action="append", default=[], metavar="KEY=VALUE",
                    help="a robot.fuzzy setting for every run, e.g. terminal_match=false peer_goals=false (ablations)")
    ap.add_argument("--table-only", action="store_true", help="rewrite OUT/chang_table.md from OUT/chang_table.json, run nothing")
    add_engine_args(ap)  # the fleet backend's runs; the numpy backend runs here, one after another
    a = ap.parse_args(argv)
    eng = engine(ap, a)
    if a.fuzzy:  # checked as the scenario reader checks robot.fuzzy: one line, exit 2
        from stack.policies.fuzzy import FuzzyConfig
        from stack.settings import SettingError, read

        try:
            read(FuzzyConfig, dict(a.fuzzy), "robot.fuzzy")
        except SettingError as e:
            ap.error(f"--fuzzy: {e}")
    a.out.mkdir(parents=True, exist_ok=True)
    if a.table_only:
        src = a.out / "chang_table.json"
        if not src.exists():
            ap.error(f"--table-only: {src} does not exist")
        results = json.loads(src.read_text())
        md = table(results, max(len(r) for r in results.values()), a.backend)
        (a.out / "chang_table.md").write_text(md + "\n")
        print(md)
        return 0
    t0 = time.perf_counter()
    keys = [(Path(scen).stem, scen, coord, loss) for scen in a.scenarios for coord in a.coordinators for loss in a.loss]
    results: dict[str, list] = {f"{name}|{coord}|{loss}": [] for name, _, coord, loss in keys}
    plan = [(k, seed) for k in keys for seed in range(a.seeds)]
    if a.backend == "fleet":
        out = a.out.resolve()
        jobs = [fleet_job(ROOT / scen, coord, seed, loss, out / f"{name}-{coord}-loss{loss:g}-s{seed}", dict(a.fuzzy))
                for (name, scen, coord, loss), seed in plan]
        done: dict[int, dict] = {}

        def keep(i: int, result) -> None:  # what has finished so far, in OUT/chang_table.json (--table-only)
            done[i] = fleet_row(result)
            (a.out / "chang_table.json").write_text(json.dumps(_by_key(plan, done), indent=1) + "\n")

        run_jobs(jobs, eng, desc="chang table", on_result=keep)
        rows = [done[i] for i in range(len(jobs))]
    else:
        rows = [numpy_run(ROOT / scen, coord, seed, loss, dict(a.fuzzy)) for (_, scen, coord, loss), seed in plan]
    for ((name, _, coord, loss), seed), r in zip(plan, rows):
        results[f"{name}|{coord}|{loss}"].append(r | {"seed": seed})
    (a.out / "chang_table.json").write_text(json.dumps(results, indent=1) + "\n")
    md = table(results, a.seeds, a.backend) + (f"\n\nrobot.fuzzy: {dict(a.fuzzy)}" if a.fuzzy else "") + f"\n\nwall time {time.perf_counter() - t0:.0f} s\n"
    (a.out / "chang_table.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
