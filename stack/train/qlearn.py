"""Fan 2021 improved Q-learning on a grid map: Q-L1..Q-L5 (Table 1-2, Fig. 5-7) or the formation (Fig. 8).

Examples:
  stack-train qlearn --map maps/fan2021-fig5.txt --variant Q-L5 --out runs/qlearn
  stack-train qlearn --map maps/fan2021-fig5.txt --variant all --seeds 10 --out runs/table2
  stack-train qlearn --formation --out runs/formation

Writes OUT/qlearn.json: the contract fields (converged, convergence_round, convergence_time_s,
steps, path_length, path) of the first seed of the variant (of Q-L5 with --variant all), and every
run under "runs"; OUT/table2.md and OUT/table2.json (mean and spread over the seeds beside the
paper's Table 2); path plots like Fig. 5 (path_<variant>.png, fig5.png) and Fig. 6-7 (curves.png).
--formation writes OUT/formation.json and OUT/formation.png (Fig. 8: without and with obstacles).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from ..argtypes import positive_int
from . import InputError

#: Table 2 of the paper (Q-L3: "No" everywhere).
PAPER_TABLE2: dict[str, dict | None] = {
    "Q-L1": {"time_s": 479.0037, "rounds": 2760, "steps": 30, "length": 37.4558},
    "Q-L2": {"time_s": 379.4773, "rounds": 3520, "steps": 30, "length": 36.0416},
    "Q-L3": None,
    "Q-L4": {"time_s": 5.7183, "rounds": 120, "steps": 26, "length": 32.6274},
    "Q-L5": {"time_s": 48.3259, "rounds": 1010, "steps": 22, "length": 28.6274},
}
DEFAULT_FORMATION_MAP = "fan2021-fig8.txt"


@dataclass
class QLearnJob:
    """What ``stack-train qlearn`` runs (built from the flags by :func:`main`)."""

    map: str | None
    """Map file (see :mod:`stack.planning.grid`); for --formation the obstacle map (default fig8)."""
    variants: list[str]
    """Variants to run, in order."""
    seeds: list[int]
    """Seeds; every variant runs once per seed."""
    out: Path
    """Output folder."""
    max_rounds: int = 10000
    """Most rounds per run (section 5.1: 10000)."""
    max_steps: int | None = None
    """Most steps per round (None: the number of cells)."""
    collision: str = "stay"
    """"stay" or "terminal" (see :mod:`stack.planning.qlearning`, reading 1)."""
    formation: bool = False
    """Run the section 5.2 formation experiment instead of the variants."""
    plots: bool = True
    """Write the PNG figures."""
    progress: bool = True
    """Show a tqdm progress bar over the runs."""



def add_arguments(p: argparse.ArgumentParser) -> None:
    from stack.planning.qlearning import VARIANTS

    p.add_argument("--map", metavar="FILE", help="ASCII map (a path, or a name under maps/); required unless --formation")
    p.add_argument("--variant", default="Q-L5", choices=VARIANTS + ("all",), help="Table 1 variant, or all (default Q-L5)")
    p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--seeds", type=positive_int, help="number of seeds S, S+1, ... (default 10 with --variant all, else 1)")
    p.add_argument("--out", type=Path, default=Path("runs/qlearn"), help="output folder (default runs/qlearn)")
    p.add_argument("--max-rounds", type=positive_int, default=10000, help="most rounds per run (default 10000)")
    p.add_argument("--max-steps", type=positive_int, help="most steps per round (default: the number of cells)")
    p.add_argument("--collision", choices=("stay", "terminal"), default="stay",
                   help="a collision keeps the robot in place (default) or ends the round")
    p.add_argument("--formation", action="store_true",
                   help="section 5.2: triangle formation with and without obstacles (Fig. 8)")
    p.add_argument("--no-plots", action="store_true", help="write no PNG")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    if args.map is None and not args.formation:
        args._parser.error("--map FILE is required (or --formation)")
    if args.formation and args.variant not in ("Q-L5",):
        args._parser.error("--formation uses the paper's leader planner Q-L5; leave --variant out")
    from stack.planning.qlearning import VARIANTS

    variants = list(VARIANTS) if args.variant == "all" else [args.variant]
    n = args.seeds or (10 if args.variant == "all" else 1)
    job = QLearnJob(map=args.map, variants=variants, seeds=list(range(args.seed, args.seed + n)), out=args.out,
                    max_rounds=args.max_rounds, max_steps=args.max_steps, collision=args.collision,
                    formation=args.formation, plots=not args.no_plots, progress=not args.no_progress)
    if job.formation:
        run_formation_job(job)
    else:
        run_qlearn(job)
    return 0


def _load(name: str):
    from stack.planning.grid import MapError, load_map

    try:
        return load_map(name)
    except MapError as e:
        raise InputError(str(e)) from None
    except (FileNotFoundError, IsADirectoryError, PermissionError) as e:
        raise InputError(str(e) if isinstance(e, FileNotFoundError) else f"{name}: {e.strerror}") from None


def _write_json(path: Path, doc) -> None:
    path.write_text(json.dumps(doc, indent=1, default=lambda o: o.item() if hasattr(o, "item") else str(o)) + "\n")


def run_qlearn(job: QLearnJob) -> dict:
    """Run every variant for every seed on the map; write qlearn.json, table2.md/json and the plots."""
    from tqdm import tqdm

    from stack.planning.qlearning import QLearningConfig, plan_map

    grid = _load(job.map)
    job.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, list] = {v: [] for v in job.variants}
    bar = tqdm(total=len(job.variants) * len(job.seeds), desc="qlearn", unit="run", disable=not job.progress,
               file=sys.stderr)
    for v in job.variants:
        for s in job.seeds:
            bar.set_postfix_str(f"{v} seed {s}")
            cfg = QLearningConfig(variant=v, seed=s, max_rounds=job.max_rounds, max_steps=job.max_steps,
                                  collision=job.collision)
            results[v].append(plan_map(grid, cfg))
            bar.update()
    bar.close()

    head_variant = "Q-L5" if "Q-L5" in results and len(job.variants) > 1 else job.variants[0]
    head = results[head_variant][0]
    rows, md = table2(results)
    doc = dict(head.summary())
    doc.update({
        "map": job.map, "shape": list(grid.shape), "variants": job.variants, "seeds": job.seeds,
        "config": {k: v for k, v in asdict(QLearningConfig(variant=head_variant, max_rounds=job.max_rounds,
                                                           max_steps=job.max_steps, collision=job.collision)).items()},
        "table2": rows,
        "runs": [r.summary() for v in job.variants for r in results[v]],
    })
    _write_json(job.out / "qlearn.json", doc)
    (job.out / "table2.md").write_text(md)
    _write_json(job.out / "table2.json", {"map": job.map, "seeds": job.seeds, "rows": rows})
    files = [job.out / "qlearn.json", job.out / "table2.md", job.out / "table2.json"]
    if job.plots:
        from stack.planning import plots

        firsts = [results[v][0] for v in job.variants]
        for r in firsts:
            files.append(plots.plot_path(r, job.out / f"path_{r.variant}.png"))
        if len(firsts) > 1:
            files.append(plots.plot_paths(firsts, job.out / "fig5.png"))
        files.append(plots.plot_curves(firsts, job.out / "curves.png"))
    print(f"map {job.map} ({grid.shape[0]} x {grid.shape[1]}), seeds {job.seeds[0]}..{job.seeds[-1]}, "
          f"collision={job.collision}")
    print(md, end="")
    print("wrote " + ", ".join(str(f) for f in files))
    return doc


def _stats(xs) -> dict | None:
    if not xs:
        return None
    m = sum(xs) / len(xs)
    sd = math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1)) if len(xs) > 1 else 0.0
    return {"mean": m, "std": sd, "min": min(xs), "max": max(xs)}


def table2(results: dict[str, list]) -> tuple[list[dict], str]:
    """Table 2 from runs grouped by variant: JSON rows and a markdown table beside the paper's numbers.
    Means and sample std over the converged runs; steps and length of the planned path."""
    from stack.planning.qlearning import FEATURES

    rows = []
    for v, runs in results.items():
        conv = [r for r in runs if r.converged]
        f = FEATURES[v]
        rows.append({
            "variant": v, "potential_field": f["gpf"], "filling": f["filling"], "reward": f["reward"],
            "epsilon": "dynamic" if f["sa"] else 0.2, "runs": len(runs), "converged": len(conv),
            "convergence_time_s": _stats([r.convergence_time_s for r in conv]),
            "convergence_round": _stats([r.convergence_round for r in conv]),
            "steps": _stats([r.steps for r in conv]), "path_length": _stats([r.path_length for r in conv]),
            "paper": PAPER_TABLE2.get(v),
        })

    def ms(st, fmt):
        return "no" if st is None else f"{fmt.format(st['mean'])} ± {fmt.format(st['std'])}"

    def pp(row, key, fmt):
        p = row["paper"]
        return "no" if p is None else fmt.format(p[key])

    lines = ["| Algorithm | Potential field | Filling | r | ε | converged | time s (mean ± sd) | paper | "
             "rounds (mean ± sd) | paper | steps | paper | length | paper |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        lines.append(" | ".join([
            f"| {row['variant']}", "yes" if row["potential_field"] else "no", "yes" if row["filling"] else "no",
            row["reward"], str(row["epsilon"]), f"{row['converged']}/{row['runs']}",
            ms(row["convergence_time_s"], "{:.3f}"), pp(row, "time_s", "{:.1f}"),
            ms(row["convergence_round"], "{:.0f}"), pp(row, "rounds", "{:d}"),
            ms(row["steps"], "{:.1f}"), pp(row, "steps", "{:d}"),
            ms(row["path_length"], "{:.2f}"), pp(row, "length", "{:.2f}") + " |"]))
    return rows, "\n".join(lines) + "\n"


def run_formation_job(job: QLearnJob) -> dict:
    """Section 5.2: leader (2, 2) -> (19, 19) with Q-L5, followers at (0, 2) and (2, 0); free and obstacle maps."""
    import numpy as np

    from stack.planning.qlearning import QLearningConfig
    from stack.planning.tracking import formation_experiment

    grid = _load(job.map or DEFAULT_FORMATION_MAP)
    job.out.mkdir(parents=True, exist_ok=True)
    seed = job.seeds[0]
    q = QLearningConfig(variant="Q-L5", seed=seed, max_rounds=job.max_rounds, max_steps=job.max_steps,
                        collision=job.collision)
    runs = {}
    for name, occ in (("free", np.zeros(grid.shape, bool)), ("obstacles", grid.occupancy)):
        try:
            runs[name] = formation_experiment(occ, grid.start, grid.goal, qconfig=q)
        except ValueError as e:  # a follower's start cell is an obstacle or off the map
            raise InputError(f"{job.map or DEFAULT_FORMATION_MAP}: {e}") from None
    doc = {"map": job.map or DEFAULT_FORMATION_MAP, "seed": seed,
           "leader_start": list(grid.start), "goal": list(grid.goal),
           **{name: {**fr.summary(), "leader_plan": fr.leader_plan.summary()} for name, fr in runs.items()}}
    _write_json(job.out / "formation.json", doc)
    files = [job.out / "formation.json"]
    if job.plots:
        from stack.planning.plots import plot_formation

        files.append(plot_formation([runs["free"], runs["obstacles"]], job.out / "formation.png",
                                    titles=["(a) without obstacles", f"(b) with obstacles ({doc['map']})"]))
    for name, fr in runs.items():
        s = fr.summary()
        print(f"{name:9s}: reached={s['reached']} ticks={s['ticks']} formation error mean {s['formation_error_mean']:.2f} "
              f"max {s['formation_error_max']:.2f} cells; path lengths leader {s['leader_path_length']:.2f}, "
              f"followers {', '.join(f'{x:.2f}' for x in s['follower_path_lengths'])}")
    print("wrote " + ", ".join(str(f) for f in files))
    return doc
