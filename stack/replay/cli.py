"""``stack-replay FILE``: a robot's recorded steps through its step pipeline again, to the bit or with a change.

    stack-replay robot.mcap                              # exit 0: every output reproduced to the bit
    stack-replay runs/diamond/run.mcap --robot-id 2      # one robot of a fleet's recording
    stack-replay robot.mcap --set robot.pid.k_w=2.5      # exit 1: "first divergence: step K ...", a table,
                                                         # DIR/replay-robot_<id>.png and .mcap
    stack-fleet replay --verify runs/diamond             # every robot of a run (exit 1 if one does not reproduce)

Open-loop: the world does not answer the replayed commands (the inputs stay the recorded robot's). Exit codes:
0 every step reproduced (or the change made no difference), 1 a step differs, 2 bad input (one line).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..agents.steplog import LogError
from ..numerics import blas_core
from ..scenario import ScenarioError, policy_names
from .run import Changes, Result, check_out_dir, describe_first, differing, largest, replay

try:  # reading MCAP needs the `sim` (or `test`) extra; a robot's core install has none of it
    from .log import RobotLog, read_log, robots_in
except ImportError as e:  # said in one line by main() / verify()
    _MISSING: ImportError | None = e
else:
    _MISSING = None

PROG = "stack-replay"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        print(f"{self.prog}: {message}", file=sys.stderr)
        sys.exit(2)


def parser() -> argparse.ArgumentParser:
    ap = _Parser(prog=PROG, description="Replay a robot's recorded step inputs through its step pipeline "
                                        "(open-loop), to the bit or with a change.")
    ap.add_argument("file", type=Path, help="stack-agent --record FILE, or a fleet's run.mcap (with --robot-id)")
    ap.add_argument("--robot-id", type=int, metavar="N", help="which robot of a fleet's recording")
    ap.add_argument("--robot", metavar="ROBOT.yaml", help="a robot settings file layered over the recorded robot's entry")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                    help="change one setting: robot.K=V for this robot's entry (robot.pid.k_w=2.5), else the "
                         "scenario's (comm.loss=0.1); repeatable")
    ap.add_argument("--policy", choices=policy_names(), help="replay with another policy")
    ap.add_argument("--out", metavar="DIR", help="where a divergence's plot and MCAP go (default: beside FILE)")
    ap.add_argument("--top", type=int, default=10, metavar="N", help="rows of the largest-differences table")
    return ap


def _progress(total: int):
    from tqdm import tqdm

    bar = tqdm(total=total, unit="step", desc="replay", leave=False, disable=not sys.stderr.isatty() or total < 2000)
    return bar, (lambda: bar.update(1))


def run_one(log: "RobotLog", changes: Changes) -> Result:
    bar, tick = _progress(log.steps)
    try:
        return replay(log, changes, tick)
    finally:
        bar.close()


def _table(res: Result, n: int) -> str:
    lines = ["| step | t [s] | v recorded | v replayed | w recorded | w replayed | differs |",
             "| ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in largest(res, n):
        a, b = r.recorded, r.replayed
        lines.append(f"| {r.step} | {r.t:.2f} | {a.v:.4f} | {b.v:.4f} | {a.w:.4f} | {b.w:.4f} | "
                     f"{', '.join(differing(a, b))} |")
    return "\n".join(lines)


def _stopped(log: "RobotLog") -> None:
    if log.stopped:
        print(f"{PROG}: {log.path}: robot {log.robot}: stopped early: {log.stopped}; {log.steps} whole steps replayed"
              + (f", {log.skipped} record(s) not replayed" if log.skipped else ""), file=sys.stderr)


def _show(res: Result, log: "RobotLog", out: Path, changes: Changes) -> list[Path]:
    from .show import plot, write_mcap

    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"replay-robot_{res.robot}"
    what = ", ".join([*(f"--set {s}" for s in changes.sets), *([f"--robot {changes.robot_file}"] if changes.robot_file
                      else []), *([f"--policy {changes.policy}"] if changes.policy else [])]) or "no change"
    return [plot(res, stem.with_suffix(".png"), f"{log.path.name}, robot {res.robot}: recorded vs replayed ({what})"),
            write_mcap(res, stem.with_suffix(".mcap"))]


def report(res: Result, log: "RobotLog", changes: Changes, out: Path | None, top: int) -> int:
    """Print the verdict; on a divergence also the table, the plot and the MCAP. The exit code."""
    n = len(res.rows)
    lives = f" ({res.segments} agent lives)" if res.segments > 1 else ""
    if res.reproduced:
        if changes.any:
            print(f"robot {res.robot}: {n} steps replayed{lives}: the change makes no difference to any output")
        else:
            print(f"robot {res.robot}: {n} steps replayed{lives}: every output reproduced to the bit (open-loop)")
        _stopped(log)
        return 0
    print(describe_first(res))
    changed = sum(1 for r in res.rows if differing(r.recorded, r.replayed))
    print(f"{changed} of {n} steps differ (open-loop: after step {res.first.step} the inputs are still the recorded "
          "robot's, the world did not answer the replayed commands); largest command differences:")
    print(_table(res, top))
    for p in _show(res, log, out or log.path.parent, changes):
        print(f"wrote {p}")
    _stopped(log)
    return 1


def _need_mcap(prog: str) -> bool:
    if _MISSING is not None:
        print(f"{prog}: reading recordings needs the Python package '{_MISSING.name or 'mcap'}' (pip install "
              "'formation-stack[sim]')", file=sys.stderr)
    return _MISSING is None


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    if not _need_mcap(PROG):
        return 2
    changes = Changes(robot_file=a.robot, sets=a.sets, policy=a.policy)
    try:
        if a.top < 1:
            raise ScenarioError(f"--top: must be >= 1, got {a.top}")
        out = check_out_dir(a.out) if a.out else None
        log = read_log(a.file, a.robot_id)
        res = run_one(log, changes)
        return report(res, log, changes, out, a.top)
    except (LogError, ScenarioError) as e:
        print(f"{PROG}: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # --out cannot be made or written
        print(f"{PROG}: {e.filename or a.out}: cannot write ({e.strerror or e})", file=sys.stderr)
        return 2


def verify(run: Path) -> int:
    """``stack-fleet replay --verify RUN``: every robot of a run's ``run.mcap``, unchanged; 1 if one does not reproduce."""
    path = run / "run.mcap" if run.is_dir() else run
    if not _need_mcap("stack-fleet replay"):
        return 2
    try:
        ids = robots_in(path)
        if not ids:
            raise LogError(f"{path}: no step records (/robot_<id>/step_io): recorded with --no-record or an older stack")
        bad, part = [], []
        for rid in ids:
            log = read_log(path, rid)
            res = run_one(log, Changes())
            if res.reproduced:
                print(f"robot {rid}: {len(res.rows)} steps: reproduced to the bit")
            else:
                bad.append(rid)
                print(f"robot {rid}: does NOT reproduce: {describe_first(res)}")
            if log.stopped:
                part.append(rid)
            _stopped(log)
    except (LogError, ScenarioError) as e:
        print(f"stack-fleet replay: {e}", file=sys.stderr)
        return 2
    if bad:
        core = blas_core()
        print(f"{path}: robots {bad} do not reproduce: a hidden input of the step, or a change since the recording"
              + (f" (or a machine whose BLAS kernels differ: this one runs OpenBLAS {core}; stack/numerics.py)" if core else ""))
        return 1
    if part:
        print(f"{path}: robots {part} reproduced only up to where their logs stop (said above): not verified whole")
        return 1
    print(f"{path}: all {len(ids)} robots reproduced to the bit")
    return 0


def cli() -> int:
    try:
        return main()
    except BrokenPipeError:  # stack-replay ... | head
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - the interpreter's flush at exit goes nowhere
        return 0


if __name__ == "__main__":
    sys.exit(main())
