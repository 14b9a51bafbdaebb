"""Held-out results: every formation policy on generated courses nobody trained, tuned or tested on.

  python bench/heldout.py --courses 34 --jobs 2 --out runs/heldout                 # the README's table
  python bench/heldout.py --courses 2 --densities low --policies pid --out runs/heldout-smoke

Courses: ``stack.fleet.courses`` with the held-out seeds HELDOUT_START .. HELDOUT_START + N - 1
(1_000_000 ..; ``docs/courses.md``), the same N seeds at every density level (so a seed keeps its
formation and robot count across densities). A policy runs on the courses that list it in
``bench.policies``: drl, aina and qlearn everywhere, pid (no obstacle avoidance) on `low` only, where
the formation's lane is free. ``--arrival N``: fuzzy and fuzzy-lstm (Chang 2020) on N held-out arrival-time
tasks (``stack.fleet.arrival_tasks``: 3-6 robots 12-45 m from one target among blocks, to arrive together),
the same seeds, in the table as density ``arrival``. Each run is one ``stack-fleet run FILE --policy P --out DIR --no-plots
--no-progress`` process (its own router and fleet name, the world, one agent per robot); ``--jobs``
of them at a time, or ``--engine dask`` (``stack.fleet.jobs``). Writes OUT/heldout.{md,json} (per policy x density: success, collision runs and
counts, timeouts, time to goal, formation error) and OUT/heldout_success.png.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetrun import engine, report_of  # noqa: E402  (bench/, beside this script)

from stack.fleet.arrival_tasks import generate_arrival_task, write_task  # noqa: E402
from stack.fleet.courses import DENSITIES, HELDOUT_SEEDS, TUNE_SEEDS, CourseError, generate_course, write_course  # noqa: E402
from stack.fleet.jobs import Job, add_engine_args, cli_task, run_jobs  # noqa: E402

POLICIES = ("drl", "aina", "qlearn", "pid", "drl-alone")
DEFAULT_POLICIES = ("drl", "aina", "qlearn", "pid")
ALONE = {"drl": {"shield": False}, "guard": {"enabled": False}, "stuck": {"detour": {"tracker": "policy"}}}
"""``drl-alone``: Bai's network without the safety layers under it (its action shield, the step's collision
guard) and driving a stuck robot's planned detour itself (not the PID path tracker, which does not see the other
robots); the hybrid strategy (PID in situation 1, nothing within d_safe) and the stuck detector as they are: the
course's own file with these settings."""
LOCKSTEP_TIMEOUT_S = 20.0
"""How long (wall) each run's world waits for an agent's command (``stack-fleet run --lockstep-timeout``; its
default is 2 s). A lock-step world runs about ten times faster than real time, so an agent that computes for 5 s
on a loaded machine (a long qlearn plan) would stand still for 50 s of sim time past that bound: the load, not the
policy, would fail the run. A robot that still misses it is counted in ``late_step_runs``. It stays below an agent's
30 s sensor timeout, so that an agent whose step stalled for another reason is given up on (and takes up the next
step) before the agents give up on the world."""
ARRIVAL_POLICIES = ("fuzzy", "fuzzy-lstm")  # Chang 2020, on generated arrival-time tasks (density "arrival")
COLUMNS = ("policy", "density", "runs", "success", "collision_runs", "robot_robot", "robot_obstacle", "timeouts",
           "errors", "time_to_goal_s", "formation_error_rms_m", "arrival_spread_steps", "min_robot_distance_m",
           "min_obstacle_distance_m", "late_step_runs")


def outcome(rep: dict | None) -> str:
    """success, collision (any), timeout (the leader never reached the goal), error (no report, or a process
    crashed), or late (reached the goal after max_time)."""
    if rep is None or rep.get("crashed"):
        return "error"
    if rep.get("success"):
        return "success"
    if sum(v or 0 for v in (rep.get("collisions") or {}).values()) > 0:
        return "collision"
    return "timeout" if rep.get("leader_time_to_goal_s") is None else "late"


def row(task: dict, rep: dict | None, err: str, wall: float) -> dict:
    """A (course, policy) task's row from its run's report."""
    col = (rep or {}).get("collisions") or {}
    r = {k: task[k] for k in ("policy", "density", "seed", "robots", "family")}
    r |= {"outcome": outcome(rep), "error": err or None, "wall_s": round(wall, 1),
          "robot_robot": col.get("robot_robot"), "robot_obstacle": col.get("robot_obstacle")}
    for k in ("leader_time_to_goal_s", "formation_error_rms_m", "min_robot_distance_m", "min_obstacle_distance_m",
              "sim_time_s", "end_reason", "arrival_spread_steps", "late_steps"):
        r[k] = (rep or {}).get(k)
    return r


def run_all(tasks: list[dict], eng, resume: bool, lockstep_timeout: float = LOCKSTEP_TIMEOUT_S) -> list[dict]:
    """Every task's row: ``--resume`` keeps the runs that have a report.json, the others go to the engine."""
    rows, todo = [], []
    for t in tasks:
        rep_path = Path(t["out"]) / "report.json"
        if resume and rep_path.exists():
            rows.append(row(t, json.loads(rep_path.read_text()), "", 0.0))
        else:
            todo.append(t)
    wait = ("--lockstep-timeout", f"{lockstep_timeout:g}")
    jobs = [Job(cli_task, (t["file"], t["out"], ("--policy", t["policy"].removesuffix("-alone"), *wait)),
                f"{t['policy']} {t['density']} {t['seed']}") for t in todo]
    return rows + [row(t, *report_of(r)) for t, r in zip(todo, run_jobs(jobs, eng, desc="held-out"))]


def _variant(c, policy: str, weights: Path | None, drl_set: dict | None = None) -> dict | None:
    """The course's ``robot`` block for ``policy`` where it differs from the course's own: ``drl-alone``'s safety
    layers off, ``--drl-weights`` and ``--drl-set`` for both drl kinds; None where it does not."""
    drl = policy.removesuffix("-alone") == "drl"
    extra = {**(drl_set or {}), **({"weights": str(weights)} if weights else {})} if drl else {}
    if not policy.endswith("-alone") and not extra:
        return None
    robot = {**c.scenario["robot"], **(ALONE if policy.endswith("-alone") else {})}
    if extra:
        robot["drl"] = {**robot.get("drl", {}), **extra}
    return robot


def plan(courses: int, densities: list[str], policies: list[str], out: Path, skip: int = 0,
         drl_weights: Path | None = None, seeds: range = HELDOUT_SEEDS, drl_set: dict | None = None) -> list[dict]:
    """Write the courses (seeds ``skip`` on into ``seeds``: the held-out range, or TUNE_SEEDS for ``--tuning``) under
    OUT/courses/<density>/ and list the runs."""
    tasks = []
    purpose = "heldout" if seeds is HELDOUT_SEEDS else "tune"
    for d in densities:
        for seed in seeds[skip:skip + courses]:
            c = generate_course(seed, density=d, purpose=purpose)
            path = write_course(c, out / "courses" / d / f"{c.scenario['name']}.yaml")
            for p in policies:
                if p.removesuffix("-alone") not in c.scenario["bench"]["policies"]:
                    continue
                file, robot = path, _variant(c, p, drl_weights, drl_set)
                if robot is not None:  # the same course, the safety layers off or other weights
                    tag = "alone" if p.endswith("-alone") else "weights"
                    file = write_course(replace(c, scenario={**c.scenario, "robot": robot}),
                                        out / "courses" / d / f"{c.scenario['name']}-{tag}.yaml")
                tasks.append({"policy": p, "density": d, "seed": seed, "robots": c.robots, "family": c.family,
                              "file": str(file), "out": str(out / "runs" / p / d / str(seed))})
    return tasks


def plan_arrival(tasks_n: int, policies: list[str], out: Path, skip: int = 0) -> list[dict]:
    """Write the held-out arrival-time tasks under OUT/courses/arrival/ and list the runs (Chang 2020's policies)."""
    tasks = []
    for seed in HELDOUT_SEEDS[skip:skip + tasks_n]:
        t = generate_arrival_task(seed, purpose="heldout")
        path = write_task(t, out / "courses" / "arrival" / f"{t.scenario['name']}.yaml")
        for p in policies:
            tasks.append({"policy": p, "density": "arrival", "seed": seed, "robots": t.robots, "family": "arrival",
                          "file": str(path), "out": str(out / "runs" / p / "arrival" / str(seed))})
    return tasks


def _mean(xs: list) -> float | None:
    xs = [x for x in xs if x is not None]
    return round(sum(xs) / len(xs), 3) if xs else None


def aggregate(rows: list[dict], policies: list[str], densities: list[str]) -> list[dict]:
    table = []
    for p in policies:
        for d in densities:
            rs = [r for r in rows if r["policy"] == p and r["density"] == d]
            if not rs:
                continue
            won = [r for r in rs if r["outcome"] == "success"]
            table.append({
                "policy": p, "density": d, "runs": len(rs), "success": round(len(won) / len(rs), 3),
                "collision_runs": sum((r["robot_robot"] or 0) + (r["robot_obstacle"] or 0) > 0 for r in rs),
                "robot_robot": sum(r["robot_robot"] or 0 for r in rs), "robot_obstacle": sum(r["robot_obstacle"] or 0 for r in rs),
                "timeouts": sum(r["outcome"] == "timeout" for r in rs), "errors": sum(r["outcome"] == "error" for r in rs),
                "time_to_goal_s": _mean([r["leader_time_to_goal_s"] for r in won]),
                "formation_error_rms_m": _mean([r["formation_error_rms_m"] for r in rs]),
                "arrival_spread_steps": _mean([r["arrival_spread_steps"] for r in won]),
                "min_robot_distance_m": min((r["min_robot_distance_m"] for r in rs if r["min_robot_distance_m"] is not None), default=None),
                "min_obstacle_distance_m": min((r["min_obstacle_distance_m"] for r in rs if r["min_obstacle_distance_m"] is not None),
                                               default=None),
                "late_step_runs": sum(bool(r.get("late_steps")) for r in rs),
            })
    return table


def markdown(table: list[dict], seeds: range, command: str, kind: str = "Held-out") -> str:
    def cell(k, v):
        if v is None:
            return "-"
        return f"{100 * v:.0f} %" if k == "success" else f"{v:.2f}" if isinstance(v, float) else str(v)

    lines = [f"{kind} seeds {seeds.start}..{seeds.stop - 1}: courses at each density (`stack.fleet.courses`, "
             "docs/courses.md) and arrival-time tasks (`stack.fleet.arrival_tasks`, density `arrival`); time to goal "
             "(the leader's) and arrival spread over successful runs; formation error RMS over all runs.", "",
             "| " + " | ".join(COLUMNS) + " |", "|" + " --- |" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell(k, r[k]) for k in COLUMNS) + " |" for r in table]
    return "\n".join(lines + ["", f"command: `{command}`", ""])


def plot(table: list[dict], policies: list[str], densities: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    policies = [p for p in policies if any(r["policy"] == p for r in table)]  # only what ran (--arrival 0: no fuzzy)
    densities = [d for d in densities if any(r["density"] == d for r in table)]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    width = 0.8 / max(1, len(policies))
    for k, p in enumerate(policies):
        xs, ys = [], []
        for i, d in enumerate(densities):
            r = next((r for r in table if r["policy"] == p and r["density"] == d), None)
            if r is not None:
                xs.append(i + (k - (len(policies) - 1) / 2) * width)
                ys.append(100 * r["success"])
        ax.bar(xs, ys, width=width, label=p)
    ax.set_xticks(range(len(densities)), densities)
    ax.set_ylim(0, 105)
    ax.set_ylabel("success [%]")
    ax.set_xlabel("obstacle density")
    ax.axhline(95, color="k", lw=0.8, ls="--")
    ax.set_title("held-out courses: success per density")
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _list(options):
    def parse(text: str) -> list[str]:
        items = [x for x in text.split(",") if x]
        bad = [x for x in items if x not in options]
        if bad or not items:
            raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(options)}, got {text!r}")
        return items
    return parse


def _settings(ap, pairs: list[str]) -> dict:
    """``--drl-set KEY=VALUE`` pairs -> {key: value}, each checked against ``DrlConfig`` (one line on an error)."""
    import dataclasses

    import yaml

    from stack.policies.drl.config import DrlConfig

    out = {}
    for p in pairs:
        key, eq, value = p.partition("=")
        if not eq or not key:
            ap.error(f"--drl-set {p!r}: expected KEY=VALUE")
        try:
            out[key] = yaml.safe_load(value)
        except yaml.YAMLError as e:
            ap.error(f"--drl-set {p!r}: the value is not YAML ({str(e).splitlines()[0]})")
    known = [f.name for f in dataclasses.fields(DrlConfig)]
    for key in out:
        if key not in known:
            ap.error(f"--drl-set {key}: not a robot.drl setting (known: {', '.join(known)})")
    try:
        DrlConfig(**out)
    except (TypeError, ValueError) as e:
        ap.error(f"--drl-set: {e}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--courses", type=int, default=34, help="held-out courses per density (default 34: 102 in all)")
    ap.add_argument("--densities", type=_list(tuple(DENSITIES)), default=list(DENSITIES))
    ap.add_argument("--policies", type=_list(POLICIES), default=list(DEFAULT_POLICIES),
                    help=f"comma-separated, of {', '.join(POLICIES)} (default {','.join(DEFAULT_POLICIES)}; drl-alone: "
                         "the network without its shield and the collision guard)")
    ap.add_argument("--arrival", type=int, default=None, metavar="N",
                    help="held-out arrival-time tasks for fuzzy and fuzzy-lstm (Chang 2020; 0: none; default 34, "
                         "with --tuning 0)")
    ap.add_argument("--arrival-policies", type=_list(ARRIVAL_POLICIES), default=list(ARRIVAL_POLICIES))
    ap.add_argument("--first-seed", type=int, default=None, metavar="S",
                    help=f"the first held-out seed (default {HELDOUT_SEEDS.start}; --tuning: {TUNE_SEEDS.start}); a seed once reported is spent: a table "
                         "after a change takes the seeds after it")
    ap.add_argument("--tuning", action="store_true",
                    help=f"courses of the tuning seeds ({TUNE_SEEDS.start}..{TUNE_SEEDS.stop - 1}, --first-seed among "
                         "them) instead of the held-out ones: for choosing between weights or settings without spending "
                         "held-out seeds (a table of these is a smoke test, not a result; no arrival tasks)")
    ap.add_argument("--drl-weights", type=Path, metavar="FILE",
                    help="drl and drl-alone run these weights (robot.drl.weights: a stack-train drl drl.pt or its .npz "
                         "export; default: the shipped ones)")
    ap.add_argument("--drl-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a robot.drl setting for drl and drl-alone (repeatable; the value is YAML), e.g. "
                         "centre_heading=false")
    ap.add_argument("--lockstep-timeout", type=float, default=LOCKSTEP_TIMEOUT_S, metavar="S",
                    help=f"how long (wall) each run's world waits for an agent's command before it goes on without it "
                         f"(default {LOCKSTEP_TIMEOUT_S:g} s; the table counts runs with such late steps)")
    ap.add_argument("--resume", action="store_true", help="keep the runs that already have a report.json")
    ap.add_argument("--out", type=Path, default=Path("runs/heldout"))
    add_engine_args(ap)
    a = ap.parse_args(argv)
    eng = engine(ap, a)
    pool = TUNE_SEEDS if a.tuning else HELDOUT_SEEDS
    a.first_seed = pool.start if a.first_seed is None else a.first_seed
    a.arrival = (0 if a.tuning else 34) if a.arrival is None else a.arrival
    if a.tuning and a.arrival:
        ap.error(f"--tuning --arrival {a.arrival}: arrival-time tasks come from held-out seeds only (give --arrival 0)")
    skip = a.first_seed - pool.start
    left = len(pool) - skip
    if a.first_seed not in pool:
        ap.error(f"--first-seed {a.first_seed}: expected a {'tuning' if a.tuning else 'held-out'} seed, "
                 f"{pool.start}..{pool.stop - 1}")
    if not a.lockstep_timeout > 0:
        ap.error(f"--lockstep-timeout {a.lockstep_timeout:g}: expected > 0 s")
    if a.drl_weights is not None and not a.drl_weights.is_file():
        ap.error(f"--drl-weights {a.drl_weights}: no such file")
    if not 0 <= a.courses <= left or not 0 <= a.arrival <= left or not a.courses + a.arrival:
        ap.error(f"--courses {a.courses}, --arrival {a.arrival}: expected 0..{left} each from seed {a.first_seed}, not both 0")
    drl_set = _settings(ap, a.drl_set)
    try:
        tasks = plan(a.courses, a.densities, a.policies, a.out.resolve(), skip,
                     a.drl_weights.resolve() if a.drl_weights else None, pool, drl_set)
        tasks += plan_arrival(a.arrival, a.arrival_policies, a.out.resolve(), skip)
        tasks.sort(key=lambda t: t["seed"])  # seed-major: a run cut short leaves whole seeds; --resume goes on
    except CourseError as e:
        print(f"heldout: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    rows = run_all(tasks, eng, a.resume, a.lockstep_timeout)
    policies, densities = a.policies + a.arrival_policies, a.densities + ["arrival"]
    rows.sort(key=lambda r: (policies.index(r["policy"]), densities.index(r["density"]), r["seed"]))
    table = aggregate(rows, policies, densities)
    command = "python bench/heldout.py " + " ".join(argv if argv is not None else sys.argv[1:])
    seeds = pool[skip:skip + max(a.courses, a.arrival)]
    md = markdown(table, seeds, command, "Tuning" if a.tuning else "Held-out") + f"wall time {time.perf_counter() - t0:.0f} s, {eng.jobs} job(s), engine {eng.engine}\n"
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "heldout.md").write_text(md)
    (a.out / "heldout.json").write_text(json.dumps({"seeds": [seeds.start, seeds.stop - 1], "densities": densities,
                                                    "policies": policies, "table": table, "runs": rows}, indent=1) + "\n")
    plot(table, policies, densities, a.out / "heldout_success.png")
    print(md)
    print(f"table: {a.out / 'heldout.md'}, {a.out / 'heldout.json'}; plot: {a.out / 'heldout_success.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
