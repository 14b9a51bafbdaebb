"""What recording costs: lock-step steps/s of the fleet bench's fleets with and without a recorder beside them.

For each size, alternately without and with ``python -m stack.fleet.record`` listening on the same router
(``--rounds`` pairs), the world's own steps/s (world.json), and the size of the run.mcap written.

    python bench/record_bench.py --sizes 4 32 --duration 20 --rounds 2
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from fleet_bench import fleet_scenario  # noqa: E402
from stack.comm.session import free_tcp_endpoint  # noqa: E402

PY = sys.executable
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


def one_run(scenario: Path, out: Path, record: bool) -> dict:
    ep = free_tcp_endpoint()
    fleet = f"rb{os.getpid()}{int(time.monotonic() * 1000) % 100000}"
    router = subprocess.Popen([PY, "-m", "stack.comm.router", "--listen", ep], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, cwd=ROOT, env=ENV)
    rec = None
    try:
        if record:
            rec = subprocess.Popen([PY, "-m", "stack.fleet.record", "--connect", ep, "--fleet", fleet, "--scenario",
                                    str(scenario), "--out", str(out)], stdout=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
            rec.stdout.readline()  # "recording fleet ...": subscribed
        subprocess.run([PY, "-m", "stack.fleet", "run", str(scenario), "--out", str(out), "--connect", ep, "--fleet",
                        fleet, "--no-progress", "--no-plots"], capture_output=True, cwd=ROOT, env=ENV, timeout=1800)
        if rec is not None:
            rec.wait(60)
    finally:
        for p in (rec, router):
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(10)
    world = json.loads((out / "world.json").read_text())
    mcap = out / "run.mcap"
    return {"steps": world["steps"], "steps_per_s": world["steps_per_s"],
            "mcap_bytes": mcap.stat().st_size if record and mcap.exists() else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 32])
    ap.add_argument("--duration", type=float, default=20.0, help="sim seconds per run")
    ap.add_argument("--rounds", type=int, default=2, help="pairs (without, with) per size")
    ap.add_argument("--out", type=Path, default=Path("runs/record_bench"))
    a = ap.parse_args()
    rows = []
    for n in a.sizes:
        a.out.mkdir(parents=True, exist_ok=True)
        path = a.out / f"bench-{n}.yaml"
        path.write_text(yaml.safe_dump(fleet_scenario(n, a.duration), sort_keys=False))
        runs = {False: [], True: []}
        for i in range(a.rounds):
            for record in (False, True):
                runs[record].append(one_run(path, a.out / f"{n}-{'rec' if record else 'plain'}-{i}", record))
        plain = statistics.median(r["steps_per_s"] for r in runs[False])
        recd = statistics.median(r["steps_per_s"] for r in runs[True])
        rows.append({"robots": n, "plain_steps_per_s": plain, "recorded_steps_per_s": recd,
                     "slowdown_pct": 100.0 * (1 - recd / plain), "mcap_mb": runs[True][-1]["mcap_bytes"] / 1e6, "runs": runs})
    print("| robots | steps/s without | steps/s recording | slower | run.mcap |")
    print("| ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['robots']} | {r['plain_steps_per_s']:.1f} | {r['recorded_steps_per_s']:.1f} | {r['slowdown_pct']:.1f} % "
              f"| {r['mcap_mb']:.1f} MB ({a.duration:g} s) |")
    (a.out / "record_bench.json").write_text(json.dumps(rows, indent=2, default=str))


if __name__ == "__main__":
    main()
