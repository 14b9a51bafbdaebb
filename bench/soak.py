"""Soak: a long real-time fleet with radio loss, its processes' memory, file descriptors and threads over time.

One real-time fleet (``--robots`` robots in a grid behind a leader on a long straight course, ``--loss`` radio
loss at every receiver) runs for ``--duration`` wall seconds; every ``--every`` seconds each of its processes
(router, world, every agent, the recorder) is read from ``/proc``: RSS (``stack.fleet.procmem``), open file
descriptors, threads. After a warm-up (the first quarter), each series gets a least-squares line; the table gives
the first and last value and the slope per hour. Then a lock-step soak (``--lockstep-s`` sim seconds) of the
same fleet, whose report must have no late step.

The bounds it checks (exit 1 beyond them): RSS growth under ``--max-mb-per-h`` MB per hour for every process,
file descriptors and threads no higher at the end than ``--max-extra`` above their value after the warm-up, no
late lock-step step. Writes ``soak.json``, ``soak.md`` and ``soak.png`` (RSS over time) to ``--out``.

    python bench/soak.py                                     # the issue's soak: 16 robots, 10 % loss, one hour
    python bench/soak.py --robots 4 --duration 60 --every 2  # a minute: that it works
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))

from fleet_bench import fleet_scenario  # noqa: E402

from stack.fleet.orchestrator import Fleet, FleetConfig  # noqa: E402
from stack.fleet.procmem import Sampler, memory_mb  # noqa: E402
from stack.fleet.procs import Proc  # noqa: E402
from stack.scenario import parse_scenario  # noqa: E402

METRICS = ("rss_mb", "fds", "threads")


def sample(pid: int) -> dict | None:
    """One process's RSS [MB], open file descriptors and threads; None once it is gone."""
    m = memory_mb(pid)
    try:
        fds = len(os.listdir(f"/proc/{pid}/fd"))
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    if m is None:
        return None
    threads = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("Threads:"))
    return {"rss_mb": round(m["rss"], 2), "fds": fds, "threads": threads}


class SeriesSampler(Sampler):
    """``procmem.Sampler`` (a Fleet's ``spawn`` that keeps every process) keeping each process's samples in time
    (RSS, file descriptors, threads) instead of its peaks."""

    def __init__(self, every_s: float):
        super().__init__(Proc, period_s=every_s)
        self.series: dict[str, list[dict]] = {}
        self._t0 = time.monotonic()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            t = round(time.monotonic() - self._t0, 2)
            for name, proc in list(self.procs.items()):
                got = sample(proc.p.pid)
                if got is not None:
                    self.series.setdefault(name, []).append({"t": t, **got})


def growth(rows: list[dict], warmup: float = 0.25) -> dict:
    """Per metric after the warm-up: first, last, and the fitted slope per hour."""
    rows = rows[int(len(rows) * warmup):]
    if len(rows) < 3:
        return {}
    t = np.array([r["t"] for r in rows])
    out = {}
    for k in METRICS:
        y = np.array([r[k] for r in rows], float)
        slope = float(np.polyfit(t, y, 1)[0]) * 3600.0 if np.ptp(t) > 0 else 0.0
        out[k] = {"first": y[0], "last": y[-1], "per_h": round(slope, 3)}
    return out


def verdicts(result: dict, a) -> list[str]:
    """The bounds broken (empty: all kept)."""
    bad = []
    for name, g in result["growth"].items():
        if not g:
            bad.append(f"{name}: too few samples")
            continue
        if g["rss_mb"]["per_h"] > a.max_mb_per_h:
            bad.append(f"{name}: RSS grows {g['rss_mb']['per_h']:.1f} MB/h > {a.max_mb_per_h:g}")
        for k in ("fds", "threads"):
            if g[k]["last"] > g[k]["first"] + a.max_extra:
                bad.append(f"{name}: {k} {g[k]['first']:.0f} -> {g[k]['last']:.0f}")
    late = result.get("lockstep", {}).get("late_steps")
    if late:
        bad.append(f"lock-step soak: {late} late steps")
    return bad


def run(a) -> dict:
    data = fleet_scenario(a.robots, a.duration)
    data["formation"]["goal"] = [a.duration * 1.2 + 100.0, 0.0]  # never reached: the fleet drives all along
    data["comm"] = {"loss": a.loss}
    data["name"] = f"soak-{a.robots}"
    sc = parse_scenario(data, data["name"] + ".yaml")
    with SeriesSampler(a.every) as s:
        code, rep = Fleet(FleetConfig(scenario=sc, out=a.out / "realtime", realtime=True, progress=False, plots=False,
                                      record=a.record), spawn=s).run()
    result = {"robots": a.robots, "loss": a.loss, "duration_s": a.duration, "every_s": a.every, "exit": code,
              "crashed": rep.get("crashed"), "sim_time_s": rep.get("sim_time_s"),
              "series": s.series, "growth": {name: growth(rows) for name, rows in sorted(s.series.items())}}
    if a.lockstep_s > 0:
        data["duration"] = a.lockstep_s
        lc, lrep = Fleet(FleetConfig(scenario=parse_scenario(data, data["name"] + ".yaml"), out=a.out / "lockstep",
                                     progress=False, plots=False, record=False)).run()
        result["lockstep"] = {"exit": lc, "sim_time_s": lrep.get("sim_time_s"), "late_steps": lrep.get("late_steps"),
                              "steps": lrep.get("steps")}
    return result


def table(result: dict) -> str:
    lines = ["| process | RSS MB, after warm-up -> end | RSS MB/h | fds | threads |", "| --- | ---: | ---: | ---: | ---: |"]
    for name, g in result["growth"].items():
        if g:
            r, f, th = g["rss_mb"], g["fds"], g["threads"]
            lines.append(f"| {name} | {r['first']:.1f} -> {r['last']:.1f} | {r['per_h']:+.1f} | "
                         f"{f['first']:.0f} -> {f['last']:.0f} | {th['first']:.0f} -> {th['last']:.0f} |")
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for name, rows in result["series"].items():
        ax.plot([r["t"] for r in rows], [r["rss_mb"] for r in rows], lw=1, label=name if not name.startswith("agent") or name == "agent 0" else None)
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("RSS [MB]")
    ax.set_title(f"soak: {result['robots']} robots, {result['loss']:.0%} loss, real time")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="soak", description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=16)
    ap.add_argument("--loss", type=float, default=0.1, help="radio loss at every receiver")
    ap.add_argument("--duration", type=float, default=3600.0, help="wall (= sim) seconds of the real-time soak")
    ap.add_argument("--every", type=float, default=10.0, help="seconds between samples")
    ap.add_argument("--lockstep-s", type=float, default=600.0, help="sim seconds of the lock-step soak (0: none)")
    ap.add_argument("--max-mb-per-h", type=float, default=20.0, help="the RSS growth bound per process [MB/h]")
    ap.add_argument("--max-extra", type=int, default=2, help="file descriptors or threads more at the end than after the warm-up")
    ap.add_argument("--record", action="store_true", help="record run.mcap too (the recorder process is sampled)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "soak")
    a = ap.parse_args(argv)
    if a.robots < 1 or a.duration <= 0 or a.every <= 0 or not 0 <= a.loss < 1:
        print("soak: --robots >= 1, --duration > 0, --every > 0 and 0 <= --loss < 1", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    result = run(a)
    bad = verdicts(result, a)
    result["broken"] = bad
    (a.out / "soak.json").write_text(json.dumps(result, indent=1))
    text = table(result)
    if "lockstep" in result:
        ls = result["lockstep"]
        text += f"\n\nlock-step soak: {ls['steps']} steps ({ls['sim_time_s']} sim s), {ls['late_steps']} late"
    (a.out / "soak.md").write_text(text + "\n")
    plot(result, a.out / "soak.png")
    print(text)
    print("bounds kept" if not bad else "bounds broken:\n  " + "\n  ".join(bad))
    print(f"written: {a.out / 'soak.json'}, {a.out / 'soak.md'}, {a.out / 'soak.png'}")
    return 0 if not bad and not result["crashed"] else 1


if __name__ == "__main__":
    sys.exit(main())
