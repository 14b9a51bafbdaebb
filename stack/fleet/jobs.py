"""Independent fleet runs side by side: ``--jobs N`` at a time on this machine (engine ``local``), or one
Dask task each on a cluster (engine ``dask``, :mod:`.jobs_dask`, the ``dist`` extra); results in plan order.

Every run gets its own fleet name (key prefix) and its own router port (:mod:`.ports`), and runs in a
child process of its own session, so a terminal's Ctrl-C reaches only this process: on Ctrl-C or
SIGTERM each running child gets one SIGTERM, its fleet stops in order (agents command zero first,
:meth:`.orchestrator.Fleet.stop`), runs not started are dropped, and ``KeyboardInterrupt`` propagates.
"""

from __future__ import annotations

import argparse
import os
import pickle
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

ENGINES = ("local", "dask")
STOP_S = 60.0
"""How long a stopped run's child gets to stop its fleet in order before SIGKILL [s]."""


class EngineError(ValueError):
    """Engine settings that cannot work (CLI: one line, exit 2)."""


@dataclass(frozen=True)
class EngineConfig:
    """Where the runs go: ``jobs`` at a time here, or on Dask (``scheduler``; none: a loopback LocalCluster of ``jobs``)."""

    engine: str = "local"
    jobs: int = 1
    scheduler: str | None = None
    allow_remote: bool = False


@dataclass(frozen=True)
class Lane:
    """What keeps a run apart from the others: its fleet name and router endpoint (None: allocated where it runs)."""

    fleet: str
    endpoint: str | None = None


@dataclass(frozen=True)
class Job:
    """One run: ``fn(lane, *args)``, ``fn`` a module-level function (pickled by reference)."""

    fn: Callable[..., Any]
    args: tuple
    label: str


class JobFailed:
    """A run whose child failed or died (its message), in the run's place among the results."""

    def __init__(self, label: str, message: str):
        self.label, self.message = label, message

    def __repr__(self) -> str:
        return f"JobFailed({self.label!r}, {self.message!r})"


def add_engine_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--jobs", type=int, default=None, metavar="N",
                    help="runs at a time (default 1; each its own fleet, router port and child process)")
    ap.add_argument("--engine", choices=ENGINES, default="local",
                    help="local (this machine) or dask (the dist extra; one task per run)")
    ap.add_argument("--scheduler", metavar="ADDRESS",
                    help="--engine dask: a running scheduler, e.g. tcp://127.0.0.1:8786 (default: a LocalCluster of --jobs)")
    ap.add_argument("--allow-remote", action="store_true", help="allow a --scheduler off loopback")


def engine_config(a: argparse.Namespace) -> EngineConfig:
    """The engine from :func:`add_engine_args`'s flags; :class:`EngineError` naming the flag."""
    if a.jobs is not None and a.jobs < 1:
        raise EngineError(f"--jobs {a.jobs}: expected at least 1")
    if a.scheduler is not None and a.engine != "dask":
        raise EngineError("--scheduler: only with --engine dask")
    if a.engine == "dask":
        from .jobs_dask import check_dask, check_scheduler

        check_dask()
        if a.scheduler is not None:
            check_scheduler(a.scheduler, a.allow_remote)
            if a.jobs is not None:
                raise EngineError("--jobs with --scheduler: the cluster's workers decide how many runs go at once")
    return EngineConfig(engine=a.engine, jobs=a.jobs or 1, scheduler=a.scheduler, allow_remote=a.allow_remote)


def lanes(n: int) -> list[Lane]:
    """``n`` fleet names no other sweep uses (a random prefix), endpoints allocated where each run starts."""
    prefix = f"j{secrets.token_hex(3)}r"
    return [Lane(fleet=f"{prefix}{i}") for i in range(n)]


# --- one run in a child process ------------------------------------------------------------------

def _interrupt_once(signum, frame) -> None:
    for sig in (signal.SIGTERM, signal.SIGINT):  # a second signal must not cut the fleet's orderly stop short
        signal.signal(sig, lambda *_: None)
    raise KeyboardInterrupt


def child_main() -> int:
    """The child: read (job, lane) from stdin, run it, write ("ok", value) or ("error", why) to stdout."""
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, _interrupt_once)
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # whatever the run prints goes to stderr: stdout carries the result only
    job, lane = pickle.load(sys.stdin.buffer)
    try:
        result = ("ok", job.fn(lane, *job.args))
    except KeyboardInterrupt:
        return 130
    except Exception as e:  # noqa: BLE001  (the run's failure is its result, with its message)
        result = ("error", f"{type(e).__name__}: {e}")
    pickle.dump(result, out)
    out.close()
    return 0


def _tail(f, n: int = 3) -> str:
    f.seek(0)
    lines = f.read().decode(errors="replace").strip().splitlines()
    return " | ".join(lines[-n:])


def _child_env() -> dict:
    """Our environment, with this ``stack`` package first on the path: the child runs the same code as we do."""
    root = str(Path(__file__).resolve().parents[2])
    path = os.environ.get("PYTHONPATH")
    return dict(os.environ, PYTHONPATH=root if not path else f"{root}{os.pathsep}{path}")


def run_isolated(job: Job, lane: Lane, stopping: Callable[[], bool]) -> tuple[str, Any]:
    """Run ``job`` in a child process of its own session; ("ok", value), ("error", why) or ("interrupted", None).
    When ``stopping()`` turns true, the child gets one SIGTERM (its fleet stops in order), SIGKILL after ``STOP_S``."""
    if stopping():
        return "interrupted", None
    if lane.endpoint is None:
        from .ports import allocate_endpoint

        lane = replace(lane, endpoint=allocate_endpoint())
    argv = [sys.executable, "-c", "import sys; from stack.fleet.jobs import child_main; sys.exit(child_main())"]
    with tempfile.TemporaryFile() as err:
        p = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, start_new_session=True,
                             env=_child_env())
        payload, termed = pickle.dumps((job, lane)), None
        while True:
            try:
                out, _ = p.communicate(payload, timeout=0.5)
                break
            except subprocess.TimeoutExpired:
                payload = None  # sent (a retry must not send it again)
                if termed is None and stopping():
                    p.send_signal(signal.SIGTERM)
                    termed = time.monotonic()
                elif termed is not None and time.monotonic() - termed > STOP_S:
                    p.kill()
        if termed is not None:
            return "interrupted", None
        if p.returncode == 0 and out:
            return pickle.loads(out)
        return "error", f"run process exited with code {p.returncode}: {_tail(err)}"


# --- engines ---------------------------------------------------------------------------------------

class Progress:
    """A bar over runs on a terminal; elsewhere one line per finished run."""

    def __init__(self, total: int, desc: str):
        from tqdm import tqdm

        self.tty, self.total, self.n = sys.stderr.isatty(), total, 0
        self.bar = tqdm(total=total, unit="run", desc=desc, file=sys.stderr, disable=not self.tty)

    def done(self, label: str, status: str) -> None:
        self.n += 1
        self.bar.set_postfix_str(f"{label}: {status}", refresh=False)
        self.bar.update(1)
        if not self.tty:
            print(f"[{self.n}/{self.total}] {label}: {status}", file=sys.stderr, flush=True)

    def close(self) -> None:
        self.bar.close()


def _local(jobs: list[Job], lanes_: list[Lane], cfg: EngineConfig, finish: Callable[[int, tuple], None]) -> None:
    stop = threading.Event()
    with ThreadPoolExecutor(max_workers=min(cfg.jobs, len(jobs))) as pool:
        futs = {pool.submit(run_isolated, j, lane, stop.is_set): i for i, (j, lane) in enumerate(zip(jobs, lanes_))}
        try:
            for fut in as_completed(futs):
                finish(futs[fut], fut.result())
        except KeyboardInterrupt:
            stop.set()  # every running child: one SIGTERM, then its fleet's orderly stop
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def _sigterm_as_interrupt():
    """SIGTERM raises KeyboardInterrupt while the runs go (main thread only); the old handler, to put back."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def on_term(signum, frame):
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, on_term)


def run_jobs(jobs: list[Job], cfg: EngineConfig = EngineConfig(), *, desc: str = "runs",
             on_result: Callable[[int, Any], None] | None = None) -> list[Any]:
    """Every job, ``cfg.jobs`` at a time (or on Dask); their values in the order of ``jobs`` (a failed one:
    :class:`JobFailed`). ``on_result(i, value)`` as each ends. Ctrl-C / SIGTERM: see the module doc."""
    results: list[Any] = [None] * len(jobs)
    bar = Progress(len(jobs), desc)

    def finish(i: int, outcome: tuple) -> None:
        kind, value = outcome
        results[i] = value if kind == "ok" else JobFailed(jobs[i].label, value or kind)
        bar.done(jobs[i].label, "done" if kind == "ok" else f"failed: {value}")
        if on_result is not None:
            on_result(i, results[i])

    old = _sigterm_as_interrupt()
    try:
        if jobs and cfg.engine == "dask":
            from .jobs_dask import run_dask

            run_dask(jobs, lanes(len(jobs)), cfg, finish)
        elif jobs:
            _local(jobs, lanes(len(jobs)), cfg, finish)
    finally:
        bar.close()
        if old is not None:
            signal.signal(signal.SIGTERM, old)
    return results


# --- what a job runs ------------------------------------------------------------------------------

def fleet_task(lane: Lane, scenario, out: Path, plots: bool = False) -> tuple[int, dict]:
    """One fleet in this process (:func:`.orchestrator.run_fleet`, no live line): (exit code, report)."""
    from .orchestrator import FleetConfig, run_fleet

    return run_fleet(FleetConfig(scenario=scenario, out=Path(out), progress=False, plots=plots, listen=lane.endpoint,
                                 fleet=lane.fleet))


def cli_task(lane: Lane, scenario: str, out: str, args: tuple = (), plots: bool = False) -> tuple[dict | None, str, float]:
    """One ``stack-fleet run SCENARIO ARGS`` process on the lane; (report or None, its last error line, wall seconds).
    Interrupted: it gets one SIGTERM (its own orderly stop) and we wait for it."""
    import json

    cmd = [sys.executable, "-m", "stack.fleet", "run", str(scenario), *args, "--out", str(out), "--no-progress",
           "--listen", lane.endpoint, "--fleet", lane.fleet, *([] if plots else ["--no-plots"])]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        stdout, stderr = p.communicate()
    except KeyboardInterrupt:
        p.send_signal(signal.SIGTERM)
        try:
            p.communicate(timeout=STOP_S)
        except subprocess.TimeoutExpired:
            p.kill()
        raise
    wall = time.perf_counter() - t0
    rep_path = Path(out) / "report.json"
    if not rep_path.exists():
        lines = (stderr or stdout).strip().splitlines()
        return None, lines[-1] if lines else f"no report (exit {p.returncode})", wall
    return json.loads(rep_path.read_text()), "", wall


def failed_fleet(why: str) -> tuple[int, dict]:
    """A :func:`fleet_task` result for a run whose child failed: exit 3, the reason as a crash."""
    return 3, {"success": False, "crashed": [{"process": "run", "exit_code": None, "sim_time_s": 0.0, "log_tail": why}]}
