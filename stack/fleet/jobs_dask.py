"""``--engine dask``: each run one Dask task (the ``dist`` extra), results gathered into the same table.

A task runs its job as :func:`.jobs.run_isolated` does locally: a child process on the worker, its
fleet on the worker's loopback (a router port from the worker host's :mod:`.ports`). Without
``--scheduler`` the runs go to a LocalCluster here: ``jobs`` worker processes, one thread each, on
127.0.0.1, no dashboard. Ctrl-C sets a Dask ``Event`` that every task watches: running ones stop
their fleet in order, the rest return at once. Run folders are written on the worker's disk; the
reports come back with the results. Workers need this project installed and the scenarios' files.
"""

from __future__ import annotations

import re
import secrets
import time
from typing import Callable

from .jobs import STOP_S, EngineConfig, EngineError, Job, Lane, run_isolated

POLL_S = 1.0
"""How often a task asks the scheduler whether the sweep was interrupted [s]."""


def check_dask() -> None:
    try:
        import distributed  # noqa: F401
    except ImportError as e:
        raise EngineError(f"--engine dask: needs the dist extra (pip install 'formation-stack[dist]'): {e}") from None


def check_scheduler(address: str, allow_remote: bool) -> str:
    """``tcp://HOST:PORT`` (or ``tls://``); off loopback only with ``allow_remote``
    (:func:`~stack.comm.session.check_endpoint`, the fleet's endpoint rule)."""
    from ..comm.session import EndpointError, check_endpoint

    m = re.fullmatch(r"(tcp|tls)://(\[[^\]]+\]|[^:/\[\]]+):(\d+)", address)
    if not m:
        raise EngineError(f"--scheduler {address}: expected tcp://HOST:PORT (or tls://), e.g. tcp://127.0.0.1:8786")
    try:
        check_endpoint(f"{m[1]}/{m[2]}:{m[3]}", allow_remote)
    except EndpointError:
        raise EngineError(f"--scheduler {address}: not a loopback address (a scheduler on another machine needs "
                          "--allow-remote)") from None
    return address


def _task(job: Job, lane: Lane, stop_name: str) -> tuple:
    """On a worker: the job in a child process, stopped in order if the sweep's stop event is set."""
    from distributed import Event

    event, last = Event(stop_name), {"t": 0.0, "set": False}

    def stopping() -> bool:
        if not last["set"] and time.monotonic() - last["t"] >= POLL_S:
            last["t"], last["set"] = time.monotonic(), event.is_set()
        return last["set"]

    return run_isolated(job, lane, stopping)


def _cluster(cfg: EngineConfig):
    """A LocalCluster whose worker processes ignore SIGINT (they inherit it ignored), so a terminal's Ctrl-C
    reaches only us and the tasks stop their runs through the stop event rather than dying with them."""
    import signal
    import threading

    from distributed import LocalCluster

    main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        return LocalCluster(n_workers=cfg.jobs, threads_per_worker=1, processes=True, host="127.0.0.1",
                            dashboard_address=None, silence_logs=40)
    finally:
        if main:
            signal.signal(signal.SIGINT, old)


def run_dask(jobs: list[Job], lanes: list[Lane], cfg: EngineConfig, finish: Callable[[int, tuple], None]) -> None:
    """Submit every job, hand each outcome to ``finish(i, outcome)`` as it ends; Ctrl-C: stop them all, re-raise."""
    from distributed import Client, Event, as_completed, wait

    cluster = None if cfg.scheduler else _cluster(cfg)
    try:
        with Client(cfg.scheduler or cluster) as client:
            tag = secrets.token_hex(4)
            stop = Event(f"stack-fleet-stop-{tag}", client=client)
            futs = [client.submit(_task, j, lane, stop.name, key=f"run-{tag}-{i}", pure=False, retries=0)
                    for i, (j, lane) in enumerate(zip(jobs, lanes))]
            index = {f.key: i for i, f in enumerate(futs)}
            try:
                for fut in as_completed(futs):
                    finish(index[fut.key], _outcome(fut))
            except KeyboardInterrupt:
                stop.set()  # running tasks SIGTERM their run's child; queued ones return at once
                wait(futs, timeout=STOP_S + 30)
                raise
    finally:
        if cluster is not None:
            cluster.close()


def _outcome(fut) -> tuple:
    try:
        return fut.result()
    except Exception as e:  # noqa: BLE001  (a worker that died, a task that could not be unpickled: that run failed)
        return "error", f"dask: {type(e).__name__}: {e}"
