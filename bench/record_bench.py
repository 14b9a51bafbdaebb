"""What recording costs: lock-step steps/s of the fleet bench's fleets with and without the fleet's recording.

For each size, ``--pairs`` pairs run interleaved (without, with, without, with, ...) so a machine whose load
drifts biases neither side: ``stack-fleet run --no-record`` against ``stack-fleet run`` (which records
``run.mcap`` in the orchestrator's process, its recorder listening on the fleet's keys). It reports the
world's own steps/s (world.json) per run, the medians, the spread, the per-pair slowdown, the recorder's
writer-thread CPU per step (the recording's ``stack.run`` metadata: a cost a loaded machine does not blur),
the run.mcap written and the load average at each run's start.

    python bench/record_bench.py --sizes 4 32 --duration 20 --pairs 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from fleet_bench import fleet_scenario  # noqa: E402

PY = sys.executable
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


def one_run(scenario: Path, out: Path, record: bool) -> dict:
    load = os.getloadavg()[0]
    argv = [PY, "-m", "stack.fleet", "run", str(scenario), "--out", str(out), "--no-progress", "--no-plots"]
    p = subprocess.run(argv + ([] if record else ["--no-record"]), capture_output=True, text=True, cwd=ROOT, env=ENV,
                       timeout=1800)
    world = json.loads((out / "world.json").read_text())
    mcap = out / "run.mcap"
    return {"record": record, "exit": p.returncode, "steps": world["steps"], "steps_per_s": world["steps_per_s"],
            "load_1min": round(load, 1), "mcap_bytes": mcap.stat().st_size if record and mcap.exists() else None,
            "writer_ms_per_step": _writer_ms(mcap, world["steps"]) if record and mcap.exists() else None}


def _writer_ms(mcap: Path, steps: int) -> float | None:
    """The recorder's writer thread's CPU per world step (its ``stack.run`` metadata), in ms."""
    from mcap.reader import make_reader

    with open(mcap, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    cpu = meta.get("stack.run", {}).get("writer_cpu_s")
    return 1000.0 * float(cpu) / steps if cpu is not None and steps else None


def summary(n: int, runs: list[dict], duration: float) -> dict:
    plain = [r["steps_per_s"] for r in runs if not r["record"]]
    recd = [r["steps_per_s"] for r in runs if r["record"]]
    pairs = [100.0 * (1 - b / a) for a, b in zip(plain, recd)]
    mcap = [r["mcap_bytes"] for r in runs if r["record"] and r["mcap_bytes"]]
    writer = [r["writer_ms_per_step"] for r in runs if r["record"] and r["writer_ms_per_step"] is not None]
    return {"robots": n, "duration_s": duration, "plain_median": statistics.median(plain), "plain_range": (min(plain), max(plain)),
            "recorded_median": statistics.median(recd), "recorded_range": (min(recd), max(recd)),
            "slowdown_median_pct": statistics.median(pairs), "slowdown_range_pct": (min(pairs), max(pairs)),
            "mcap_mb": statistics.median(mcap) / 1e6 if mcap else None,
            "writer_ms_per_step": statistics.median(writer) if writer else None,
            "load_1min": (min(r["load_1min"] for r in runs), max(r["load_1min"] for r in runs)), "runs": runs}


def table(rows: list[dict]) -> str:
    lines = ["| robots | pairs | steps/s without (median, range) | steps/s recording (median, range) | slower, per pair (median, range) | writer CPU per step | run.mcap | load (1 min) |",
             "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['robots']} | {len(r['runs']) // 2} | {r['plain_median']:.1f} ({r['plain_range'][0]:.1f}-{r['plain_range'][1]:.1f}) "
                     f"| {r['recorded_median']:.1f} ({r['recorded_range'][0]:.1f}-{r['recorded_range'][1]:.1f}) "
                     f"| {r['slowdown_median_pct']:.1f} % ({r['slowdown_range_pct'][0]:.1f} to {r['slowdown_range_pct'][1]:.1f} %) "
                     f"| {r['writer_ms_per_step'] or 0:.2f} ms | {r['mcap_mb']:.1f} MB ({r['duration_s']:g} s) | {r['load_1min'][0]:g}-{r['load_1min'][1]:g} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 32])
    ap.add_argument("--duration", type=float, default=20.0, help="sim seconds per run")
    ap.add_argument("--pairs", type=int, default=3, help="interleaved pairs (without, with) per size")
    ap.add_argument("--out", type=Path, default=Path("runs/record_bench"))
    a = ap.parse_args()
    rows = []
    for n in a.sizes:
        a.out.mkdir(parents=True, exist_ok=True)
        path = a.out / f"bench-{n}.yaml"
        path.write_text(yaml.safe_dump(fleet_scenario(n, a.duration), sort_keys=False))
        runs = []
        for i in range(a.pairs):
            for record in (False, True):
                runs.append(one_run(path, a.out / f"{n}-{'rec' if record else 'plain'}-{i}", record))
                r = runs[-1]
                print(f"{n} robots, pair {i}, {'recording' if record else 'without  '}: {r['steps_per_s']:.1f} steps/s "
                      f"(load {r['load_1min']})", file=sys.stderr, flush=True)
        rows.append(summary(n, runs, a.duration))
        (a.out / "record_bench.json").write_text(json.dumps(rows, indent=2, default=str))
    print(table(rows))


if __name__ == "__main__":
    main()
