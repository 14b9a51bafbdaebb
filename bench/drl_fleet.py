"""Bai 2022 Fig. 9-11 in the fleet: ``--policy drl`` on three obstacle layouts, a few seeds, one table.

  python bench/drl_fleet.py --seeds 3 --out runs/drl-fleet --figures docs/figures     # the README's table
  python bench/drl_fleet.py --drl shield=false --out runs/drl-fleet-noshield          # the network alone
  python bench/drl_fleet.py --drl leader_hold=null --out runs/drl-fleet-eq20          # eq. (20) alone

Each run is one ``stack-fleet run SCENARIO --policy drl --seed K`` process (router, pybullet world, one
agent per robot); ``--jobs N`` of them at a time, or ``--engine dask`` (``stack.fleet.jobs``). ``--drl KEY=VALUE`` sets a ``robot.drl`` field on a copy of each scenario. Per run:
success, collisions, min / max robot distance (targets: >= 2 R_d, < d_com), min obstacle distance and
the steps at which the shield overruled the network. Writes OUT/drl_fleet.{md,json}; with ``--figures``
the seed-0 trajectory and distance plots are copied there as ``bai-drl-<scenario>-*.png``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetrun import engine, report_of, scenario_with, setting  # noqa: E402  (bench/, beside this script)

from stack.fleet.jobs import Job, add_engine_args, cli_task, run_jobs  # noqa: E402

SCENARIOS = ["scenarios/four-robot-obstacles.yaml", "scenarios/six-robot.yaml", "scenarios/bai-case2.yaml"]


def summary(rep: dict) -> dict:
    col = rep["collisions"]
    return {"success": rep["success"], "collisions": (col["robot_robot"] or 0) + (col["robot_obstacle"] or 0),
            "min_robot_m": rep["min_robot_distance_m"], "max_robot_m": rep["max_robot_distance_m"],
            "min_obstacle_m": rep["min_obstacle_distance_m"], "leader_at_goal_s": rep["leader_time_to_goal_s"],
            "shield_masked": [r.get("shield_masked") for r in rep["robots"].values()]}


def table(results: dict, d_com: dict) -> str:
    seeds = max(len(v) for v in results.values())
    lines = ["| scenario | " + " | ".join(f"seed {k}" for k in range(seeds)) + " |",
             "| --- |" + " --- |" * seeds]
    for name, runs in results.items():
        cells = []
        for r in runs:
            if "error" in r:
                cells.append(f"error: {r['error']}")
                continue
            far = r["max_robot_m"] is not None and r["max_robot_m"] >= d_com[name]
            mx = f"**{r['max_robot_m']:.2f}**" if far else f"{r['max_robot_m']:.2f}"
            cells.append(f"{'yes' if r['success'] else 'no'}, {r['collisions']}, {r['min_robot_m']:.2f} / {mx}, "
                         f"{r['min_obstacle_m']:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", type=lambda s: [x for x in s.split(",") if x], default=SCENARIOS)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("runs/drl-fleet"))
    ap.add_argument("--figures", type=Path, default=None, help="copy the seed-0 plots here (bai-drl-<scenario>-*.png)")
    ap.add_argument("--drl", type=setting("--drl", "drl"), action="append", default=[], metavar="KEY=VALUE",
                    help="a robot.drl setting for every run, e.g. shield=false or leader_hold=null")
    add_engine_args(ap)
    a = ap.parse_args(argv)
    eng = engine(ap, a)
    if a.seeds < 1:
        ap.error(f"--seeds {a.seeds}: expected at least 1")
    if a.drl:  # checked as the scenario reader checks robot.drl: one line, exit 2
        from stack.policies.drl.config import DrlConfig
        from stack.settings import SettingError, read

        try:
            read(DrlConfig, dict(a.drl), "robot.drl")
        except SettingError as e:
            ap.error(f"--drl: {e}")
    from stack.scenario import ScenarioError, load_scenario

    d_com = {}
    for scen in a.scenarios:
        try:
            d_com[Path(scen).stem] = min(r.comm_range for r in load_scenario(ROOT / scen).robots)
        except (OSError, ScenarioError) as e:
            ap.error(f"--scenarios {scen}: {e}")
    a.out.mkdir(parents=True, exist_ok=True)
    out = a.out.resolve()
    plan = [(Path(scen).stem, seed, scenario_with(ROOT / scen, "drl", dict(a.drl), out, "drl"))
            for scen in a.scenarios for seed in range(a.seeds)]
    jobs = [Job(cli_task, (str(path), str(out / f"{name}-s{seed}"), ("--policy", "drl", "--seed", str(seed)),
                           a.figures is not None and seed == 0), f"{name} seed {seed}") for name, seed, path in plan]
    t0 = time.perf_counter()
    results: dict[str, list] = {Path(scen).stem: [] for scen in a.scenarios}
    for (name, seed, _), res in zip(plan, run_jobs(jobs, eng, desc="drl fleet")):
        rep, err, wall = report_of(res)
        r = ({"error": err} if rep is None else summary(rep)) | {"seed": seed, "wall_s": round(wall, 1)}
        results[name].append(r)
        print(f"{name} seed {seed}: {r}", file=sys.stderr, flush=True)
        if a.figures is not None and seed == 0 and rep is not None:
            a.figures.mkdir(parents=True, exist_ok=True)
            for kind in ("trajectories", "distances"):
                src = out / f"{name}-s{seed}" / f"{kind}.png"
                if src.exists():
                    shutil.copy(src, a.figures / f"bai-drl-{name}-{kind}.png")
    (a.out / "drl_fleet.json").write_text(json.dumps(results, indent=1) + "\n")
    md = ("columns: success, collisions, min / max robot distance [m] (bold: >= d_com), min obstacle distance [m]\n\n"
          + table(results, d_com) + (f"\n\nrobot.drl: {dict(a.drl)}" if a.drl else "")
          + f"\n\nwall time {time.perf_counter() - t0:.0f} s\n")
    (a.out / "drl_fleet.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
