"""``stack-fleet bench``: every scenario under a folder x every implemented policy it is meant for.

One lock-step run each (the scenario's seed, or ``--seed``); one table in markdown and
JSON beside the runs, with the paper's reference figure of each scenario in the last column.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ..policies import available
from ..scenario import ScenarioError, load_scenario, with_overrides
from .orchestrator import FleetConfig, run_fleet

COLUMNS = ("scenario", "policy", "success", "sim_time_s", "leader_time_to_goal_s", "collisions", "min_robot_distance_m",
           "max_robot_distance_m", "min_obstacle_distance_m", "formation_error_rms_m", "connectivity", "convergence_s",
           "formation_recovery_s", "wall_time_s")


def _cell(v) -> str:
    if isinstance(v, dict):
        return "/".join(str(x) for x in v.values())
    if isinstance(v, float):
        return f"{v:.2f}"
    return "-" if v is None else str(v)


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


def main(folder: Path, out: Path, seed: int | None = None) -> int:
    files = sorted(folder.glob("*.yaml"))
    if not files:
        print(f"stack-fleet bench: {folder}: no scenario files", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    impl = set(available())
    rows, skipped = [], []
    plan = []
    for f in files:
        try:
            sc = load_scenario(f)
        except ScenarioError as e:
            print(f"stack-fleet bench: {e}", file=sys.stderr)
            return 2
        for pol in sc.bench.policies:
            (plan if pol in impl else skipped).append((f, sc, pol))
    for n, (f, sc, pol) in enumerate(plan, 1):
        run = with_overrides(sc, policy=pol, seed=seed)
        dest = out / f"{sc.name}-{pol}"
        print(f"[{n}/{len(plan)}] {sc.name} with {pol} ...", file=sys.stderr, flush=True)
        code, rep = run_fleet(FleetConfig(scenario=run, out=dest, progress=sys.stderr.isatty()))
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
        lines.append("Not run (policy not implemented yet): " + ", ".join(f"{sc.name}/{p}" for _, sc, p in skipped))
    table = "\n".join(lines)
    (out / "bench.md").write_text(table + "\n")
    (out / "bench.json").write_text(json.dumps({"runs": rows, "skipped": [[sc.name, p] for _, sc, p in skipped]}, indent=2))
    print(table)
    print(f"\ntable: {out / 'bench.md'}, {out / 'bench.json'}")
    return 0 if all(r["exit"] == 0 for r in rows) else 1
