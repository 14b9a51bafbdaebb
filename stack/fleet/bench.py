"""``stack-fleet bench``: every scenario under a folder x every implemented policy it is meant for.

One lock-step run each (the scenario's seed, or ``--seed``; ``--jobs N`` at a time, or on Dask: :mod:`.jobs`);
one table in markdown and JSON beside the runs, with the paper's reference figure of each scenario in the last column.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ..policies import available
from ..scenario import POLICIES, ScenarioError, load_scenario, with_overrides
from .jobs import EngineConfig, Job, JobFailed, failed_fleet, fleet_task, run_jobs

COLUMNS = ("scenario", "policy", "success", "sim_time_s", "leader_time_to_goal_s", "collisions", "min_robot_distance_m",
           "max_robot_distance_m", "min_obstacle_distance_m", "formation_error_rms_m", "connectivity", "convergence_s",
           "formation_recovery_s", "wall_time_s")


def _cell(v) -> str:
    if isinstance(v, dict):
        return "/".join(str(x) for x in v.values())
    if isinstance(v, float):
        return f"{v:.2f}"
    return "-" if v is None else str(v)


def _plan(folder: Path, policies: list[str] | None = None) -> tuple[list, list]:
    """(scenario, policy) pairs to run from every scenario file in ``folder`` (each scenario's
    ``bench.policies``, or ``policies``), and those skipped because the policy is not implemented."""
    files = sorted(folder.glob("*.yaml"))
    if not files:
        raise ScenarioError(f"{folder}: no scenario files")
    impl = set(available())
    plan, skipped = [], []
    for f in files:
        sc = load_scenario(f)
        for pol in policies or sc.bench.policies:
            (plan if pol in impl else skipped).append((sc, pol))
    return plan, skipped


def convergence_cell(rep: dict) -> str | None:
    """Followers' error_convergence_time_s x/y, counted from the last formation switch (Deng Tables 1-2)."""
    t0 = max(rep.get("formation_switches_s") or [0.0])
    cells = []
    for rid, r in sorted(rep.get("robots", {}).items(), key=lambda kv: int(kv[0])):
        if r.get("role") != "follower":
            continue
        c = r["error_convergence_time_s"]
        xy = ["never" if c[a] is None else f"{max(0.0, c[a] - t0):.1f}" for a in ("x", "y")]
        cells.append(f"{rid}: {xy[0]}/{xy[1]}")
    return "; ".join(cells) or None


def main(folder: Path, out: Path, seed: int | None = None, policies: list[str] | None = None,
         engine: EngineConfig = EngineConfig()) -> int:
    """The bench over ``folder``; ``policies``: these instead of each scenario's ``bench.policies``;
    ``engine``: where the runs go (:mod:`.jobs`)."""
    try:
        plan, skipped = _plan(folder, policies)
    except ScenarioError as e:
        print(f"stack-fleet bench: {e}", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    jobs = [Job(fleet_task, (with_overrides(sc, policy=pol, seed=seed), (out / f"{sc.name}-{pol}").resolve(), True),
                f"{sc.name} with {pol}") for sc, pol in plan]
    for (sc, pol), res in zip(plan, run_jobs(jobs, engine, desc="bench")):
        dest = out / f"{sc.name}-{pol}"
        code, rep = failed_fleet(res.message) if isinstance(res, JobFailed) else res
        row = {c: rep.get(c) for c in COLUMNS} | {"policy": pol, "exit": code, "reference": sc.bench.reference,
                                                 "report": str(dest / "report.json"),
                                                 "convergence_s": convergence_cell(rep)}
        rows.append(row)
    head = "| " + " | ".join(COLUMNS + ("paper",)) + " |"
    lines = [head, "|" + " --- |" * (len(COLUMNS) + 1)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r[c]) for c in COLUMNS) + f" | {r['reference']} |")
    if skipped:
        lines.append("")
        lines.append("Not run (policy not implemented yet): " + ", ".join(f"{sc.name}/{p}" for sc, p in skipped))
    table = "\n".join(lines)
    (out / "bench.md").write_text(table + "\n")
    (out / "bench.json").write_text(json.dumps({"runs": rows, "skipped": [[sc.name, p] for sc, p in skipped]}, indent=2))
    print(table)
    print(f"\ntable: {out / 'bench.md'}, {out / 'bench.json'}")
    return 0 if all(r["exit"] == 0 for r in rows) else 1


def random_bench(n: int, out: Path, *, first_seed: int = 0, robots: int | None = None, formation: str | None = None,
                 density: str | None = None, policies: list[str] | None = None, seed: int | None = None,
                 engine: EngineConfig = EngineConfig()) -> int:
    """``stack-fleet bench --random N``: the generated courses of seeds first_seed .. first_seed + N - 1
    (``stack.fleet.courses``; never the held-out seeds), written to OUT/courses/, then the bench over them."""
    from .courses import CourseError, random_scenarios, write_course

    bad = [p for p in (policies or []) if p not in POLICIES]
    if bad:
        print(f"stack-fleet bench: --policies: unknown policy {bad[0]!r} (one of {', '.join(POLICIES)})", file=sys.stderr)
        return 2
    try:
        courses = random_scenarios(n, first_seed, robots, formation, density)
    except CourseError as e:
        print(f"stack-fleet bench: {e}", file=sys.stderr)
        return 2
    folder = out / "courses"
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.yaml"):  # the folder is the bench's plan: only this call's courses
        old.unlink()
    for c in courses:
        write_course(c, folder / f"{c.scenario['name']}.yaml")
    return main(folder, out, seed=seed, policies=policies, engine=engine)


# --- sweeps (issue 9): one comm parameter over values x seeds, per scenario and policy ------------

SWEEPS = {"loss": "loss", "latency_ms": "latency_ms", "burst": "burst_loss"}
SWEEP_COLUMNS = ("scenario", "policy", "value", "runs", "crashed", "success_rate", "followers_at_slot", "collisions",
                 "min_robot_distance_m", "formation_error_rms_m", "connectivity", "delivered_share")
AT_SLOT_M = 1.0
"""A follower whose final error is within this [m] of its slot counts in ``followers_at_slot`` (success
judges the leader only, by the contract: a stranded follower shows here)."""


def parse_sweep(text: str) -> tuple[str, list[float]]:
    """``loss=0,0.1,0.2`` -> ("loss", [0.0, 0.1, 0.2]); ValueError naming what is wrong."""
    name, _, values = text.partition("=")
    if name not in SWEEPS or not values:
        raise ValueError(f"expected PARAM=V1,V2,... with PARAM one of {', '.join(SWEEPS)}, got {text!r}")
    out = []
    for v in values.split(","):
        try:
            x = float(v)
        except ValueError:
            raise ValueError(f"{name}: {v!r} is not a number") from None
        if x < 0 or (name != "latency_ms" and x > 1):
            raise ValueError(f"{name}: {v} out of range ({'>= 0' if name == 'latency_ms' else '0..1'})")
        out.append(x)
    return name, out


def sweep(folder: Path, out: Path, param: str, values: list[float], *, seeds: int = 3,
          policies: list[str] | None = None, duration: float | None = None, engine: EngineConfig = EngineConfig()) -> int:
    """Every scenario under ``folder`` x its implemented policies (or ``policies``) x ``values`` x
    ``seeds`` (seeds 0..seeds-1): one table (markdown + JSON) and one plot, ``<param>_sweep.png``."""
    try:
        plan, _ = _plan(folder, policies)
    except ScenarioError as e:
        print(f"stack-fleet bench: {e}", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    cells = [(sc, pol, value) for sc, pol in plan for value in values]
    jobs = [Job(fleet_task, (with_overrides(sc, policy=pol, seed=s, duration=duration, **{SWEEPS[param]: value}),
                             (out / f"{sc.name}-{pol}-{param}{value:g}-s{s}").resolve()),
                f"{sc.name}/{pol} {param}={value:g} seed {s}")
            for sc, pol, value in cells for s in range(seeds)]
    results = [failed_fleet(r.message) if isinstance(r, JobFailed) else r
               for r in run_jobs(jobs, engine, desc=f"{param} sweep")]
    crashed_any = any(code == 3 for code, _ in results)
    rows = [_aggregate(sc.name, pol, value, [rep | {"_exit": code} for code, rep in results[k * seeds:(k + 1) * seeds]])
            for k, (sc, pol, value) in enumerate(cells)]
    lines = ["| " + " | ".join(SWEEP_COLUMNS) + " |", "|" + " --- |" * len(SWEEP_COLUMNS)]
    lines += ["| " + " | ".join(_cell(r[c]) for c in SWEEP_COLUMNS) + " |" for r in rows]
    table = "\n".join(lines)
    (out / f"{param}_sweep.md").write_text(table + "\n")
    (out / f"{param}_sweep.json").write_text(json.dumps({"param": param, "values": values, "seeds": seeds, "rows": rows},
                                                        indent=2))
    _plot_sweep(rows, param, out / f"{param}_sweep.png")
    print(table)
    print(f"\ntable: {out / f'{param}_sweep.md'}; plot: {out / f'{param}_sweep.png'}")
    return 3 if crashed_any else 0  # a run that did not meet its goal is a result; one that crashed is not


def _aggregate(scenario: str, policy: str, value: float, reps: list[dict]) -> dict:
    def vals(key):
        return [r[key] for r in reps if r.get(key) is not None]

    crashed = [r for r in reps if r.get("_exit") == 3 or r.get("crashed")]
    finals = [v.get("final_error_m") for r in reps for v in (r.get("robots") or {}).values() if v.get("role") == "follower"]
    comm = [r.get("comm", {}) for r in reps]
    sent = sum(c.get("sent", 0) for c in comm)
    delivered = sum(c.get("delivered", 0) for c in comm)
    return {
        "scenario": scenario, "policy": policy, "value": value, "runs": len(reps), "crashed": len(crashed),
        "success_rate": sum(bool(r.get("success")) for r in reps) / len(reps),
        "followers_at_slot": sum(f is not None and f <= AT_SLOT_M for f in finals) / len(finals) if finals else None,
        # a run that crashed before its world wrote anything has no counts (None): it is in "crashed"
        "collisions": sum(sum(v or 0 for v in (r.get("collisions") or {}).values()) for r in reps),
        "min_robot_distance_m": min(vals("min_robot_distance_m"), default=None),
        "formation_error_rms_m": float(sum(vals("formation_error_rms_m")) / len(vals("formation_error_rms_m")))
        if vals("formation_error_rms_m") else None,
        "connectivity": float(sum(vals("connectivity")) / len(vals("connectivity"))) if vals("connectivity") else None,
        "delivered_share": delivered / sent if sent else None,
    }


def _plot_sweep(rows: list[dict], param: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import MaxNLocator

    panels = (("success_rate", "success rate"), ("collisions", "collisions (all seeds)"),
              ("min_robot_distance_m", "min robot distance [m]"), ("formation_error_rms_m", "formation error RMS [m]"),
              ("connectivity", "connectivity"))
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 4.2))
    keys = sorted({(r["scenario"], r["policy"]) for r in rows})
    markers = "osD^v<>ph*"
    span = max((r["value"] for r in rows), default=1.0) or 1.0
    for n, (sc, pol) in enumerate(keys):
        rs = sorted((r for r in rows if (r["scenario"], r["policy"]) == (sc, pol)), key=lambda r: r["value"])
        # a small offset per series, so equal series (e.g. every policy at 100 %) stay visible side by side
        x = [r["value"] + (n - (len(keys) - 1) / 2) * 0.006 * span for r in rs]
        for ax, (key, _) in zip(axes, panels):
            y = [r[key] if r[key] is not None else float("nan") for r in rs]
            ax.plot(x, y, marker=markers[n % len(markers)], linestyle="-", markersize=5, alpha=0.8, label=f"{sc} / {pol}")
    for ax, (key, title) in zip(axes, panels):
        ax.set_xlabel({"loss": "loss probability", "latency_ms": "latency [ms]", "burst": "mean burst loss"}[param])
        ax.set_ylabel(title)
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[0].set_ylim(-0.05, 1.05)
    axes[1].set_ylim(-0.5, max([r["collisions"] or 0 for r in rows] + [1]) + 0.5)
    axes[1].yaxis.set_major_locator(MaxNLocator(integer=True))
    axes[4].set_ylim(-0.05, 1.05)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 5), fontsize=8)
    fig.subplots_adjust(bottom=0.25)
    fig.suptitle(f"{param} sweep")
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
