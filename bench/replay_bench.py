"""Replay benchmark: how fast a robot's step log replays, against the step's own cost, and how big a log is.

For each policy, one lock-step ``stack-fleet run`` (four robots, ``--duration`` s of sim time, recording on) of
``--scenario``; then, per robot, from its ``/robot_<id>/step_io`` records in ``run.mcap``:

- **replay**: read and decode the log, rebuild the pipeline, every step through it and compared to the bit
  (``stack.replay.run.replay``: what ``stack-replay`` does), steps/s;
- **the step alone**: the same steps' ``StepPipeline.step`` on inputs decoded beforehand (the floor: what the
  agent's control step costs on this machine, without Zenoh or a driver), steps/s;
- **size** per robot-minute of the step log: the records as JSON, and zstd-compressed (as in the MCAP), with the
  scans and without them (the same records with ``scan`` left out: what the rest of the inputs cost).

    python bench/replay_bench.py                           # pid, aina, drl; 60 s of four-robot-obstacles
    python bench/replay_bench.py --policies pid --duration 20
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import msgspec  # noqa: E402
import yaml  # noqa: E402
import zstandard  # noqa: E402

from stack.agents import steplog  # noqa: E402
from stack.replay.log import _raw, read_log, robots_in  # noqa: E402
from stack.replay.run import Changes, pipeline_of, replay  # noqa: E402


def _run(scenario: Path, policy: str, duration: float, out: Path) -> Path:
    p = subprocess.run([sys.executable, "-m", "stack.fleet", "run", str(scenario), "--out", str(out), "--policy", policy,
                        "--duration", f"{duration:g}", "--no-plots", "--no-progress"], cwd=ROOT, capture_output=True,
                       text=True)
    if not (out / "run.mcap").exists():
        sys.exit(f"{policy}: the run left no run.mcap (exit {p.returncode}): {p.stderr[-600:]}")
    return out / "run.mcap"


def _sizes(path: Path, rid: int, minutes: float) -> dict:
    """Bytes per robot-minute of the records as stored (a fleet's: states by name): JSON and zstd, with and without
    scans (zstd over the whole log, as a chunk does)."""
    stored = [p for p, _ in _raw(path).steps[rid]]
    full = b"\n".join(stored)
    docs = [msgspec.json.decode(p) for p in stored]
    bare = b"\n".join(msgspec.json.encode({k: v for k, v in d.items() if k not in ("scan", "scan_same")}) for d in docs)
    z = zstandard.ZstdCompressor(level=3)
    return {"json_kib_per_min": len(full) / 1024 / minutes, "json_no_scans_kib_per_min": len(bare) / 1024 / minutes,
            "zstd_kib_per_min": len(z.compress(full)) / 1024 / minutes,
            "zstd_no_scans_kib_per_min": len(z.compress(bare)) / 1024 / minutes}


def _speeds(path: Path, rid: int) -> dict:
    t0 = time.perf_counter()
    log = read_log(path, rid)
    res = replay(log, Changes())
    t_replay = time.perf_counter() - t0
    assert res.reproduced, f"robot {rid} does not reproduce"
    seg = log.segments[0]
    pl = pipeline_of(seg.setup, Changes())
    inputs, scan = [], None
    for rec in seg.records:
        inputs.append(steplog.inputs_of(rec, scan))
        scan = inputs[-1].scan
    t0 = time.perf_counter()
    for inp in inputs:
        pl.step(inp)
    t_step = time.perf_counter() - t0
    n = len(res.rows)
    return {"steps": n, "replay_steps_per_s": n / t_replay, "step_alone_steps_per_s": len(inputs) / t_step}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", type=Path, default=ROOT / "scenarios" / "four-robot-obstacles.yaml")
    ap.add_argument("--policies", nargs="+", default=["pid", "aina", "drl"])
    ap.add_argument("--duration", type=float, default=60.0, help="sim seconds per run")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "replay-bench.json")
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for policy in a.policies:
            path = _run(a.scenario, policy, a.duration, Path(tmp) / policy)
            per = []
            for rid in robots_in(path):
                log = read_log(path, rid)
                minutes = log.steps * yaml.safe_load(log.segments[0].setup.scenario)["dt"] / 60  # lock-step: a dt a record
                per.append(_speeds(path, rid) | _sizes(path, rid, minutes))
            row = {"policy": policy, "robots": len(per)} | {k: statistics.median(p[k] for p in per) for k in per[0]}
            row["replay_vs_step"] = row["replay_steps_per_s"] / row["step_alone_steps_per_s"]
            rows.append(row)
    print(f"\nreplay of {a.scenario.name}, {a.duration:g} s lock-step runs (medians over the robots):\n")
    print("| policy | steps | replay steps/s | step alone steps/s | replay / step | log KiB/robot-min JSON (no scans) "
          "| zstd (no scans) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['policy']} | {r['steps']:.0f} | {r['replay_steps_per_s']:.0f} | {r['step_alone_steps_per_s']:.0f} | "
              f"{r['replay_vs_step']:.2f} | {r['json_kib_per_min']:.0f} ({r['json_no_scans_kib_per_min']:.0f}) | "
              f"{r['zstd_kib_per_min']:.0f} ({r['zstd_no_scans_kib_per_min']:.0f}) |")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(rows, indent=1))
    print(f"\nwrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
