"""Planning beside the control step: a plan is a job, run where it cannot hold the step.

A planner that can take seconds (Fan's Q-learning on a large grid) must not run inside a control step: on a
real robot the driver's watchdog would stop the robot, or the robot would drive on an old command. So a policy
asks for a plan with :meth:`PlanRunner.submit`: ``fn`` is a pure function of a snapshot the policy took at the
step that asks (copies, never the policy's live state), and ``on_done(result)`` adopts it on the control thread,
at the start of a later step (:meth:`PlanRunner.begin`). Meanwhile the policy drives its last good plan or its
fallback. One job at a time per ``lane`` (:meth:`busy`).

When a job is adopted is the runner's rule, the only thing the runners differ in:

- :class:`PlanRunner` (inline): at once, inside ``submit`` (a policy alone in a test or a bench: the old way);
- :class:`ThreadRunner` real time (``lockstep_steps=None``): on a worker thread, adopted at the first step that
  begins after it finished, whatever the wall clock did;
- :class:`ThreadRunner` lock-step (``lockstep_steps=n``): on the worker thread, adopted at the step ``n`` after
  the one that asked, waiting for it there if it is not done (sim time: the plan took ``n`` steps), so a run
  is the same to the bit however fast the machine is;
- :class:`ScriptedRunner` (replay): at the steps the robot's log says (``StepRecord.plans``), computed then.

Every step's adopted tickets (:attr:`adopted_now`) go into the robot's step log, so a real-time run replays
to the bit too. :meth:`stats` gives the report and the live view the plans' compute times and ages.
"""

from __future__ import annotations

import logging
import math
import queue
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger("stack.planning")

SWITCH_INTERVAL_S = 0.0005
"""The interpreter's thread switch interval while a worker runs (Python's default 5 ms): a pure-Python planner
holding the GIL gives it back to the control thread within this."""
WAIT_WARN_S = 1.0
"""Lock-step: a job still running this long after its step is due is logged (once)."""


@dataclass
class _Job:
    ticket: int
    lane: str
    fn: Callable[[], Any]
    on_done: Callable[[Any], None]
    step: int
    t: float
    """The step and step time that asked."""
    done: threading.Event = field(default_factory=threading.Event)
    result: Any = None
    error: BaseException | None = None
    ms: float = 0.0
    """Wall time the job computed [ms]."""

    def run(self) -> None:
        t0 = time.perf_counter()
        try:
            self.result = self.fn()
        except BaseException as e:  # noqa: BLE001 - raised again on the control thread, at adoption
            self.error = e
        self.ms = (time.perf_counter() - t0) * 1e3
        self.done.set()


class PlanRunner:
    """Inline: a job runs and is adopted inside :meth:`submit`. The base of every runner: tickets, lanes, stats."""

    mode = "inline"

    def __init__(self) -> None:
        self.pending: dict[int, _Job] = {}
        self.tickets = 0
        self.step, self.t = -1, 0.0
        self.adopted_now: list[int] = []
        """The tickets adopted in the current step (the step log's ``plans``)."""
        self.adopted = 0
        self.times_ms: deque[float] = deque(maxlen=2000)
        self.waits: deque[float] = deque(maxlen=2000)
        """[s] step time from asking to adopting, each adopted plan."""
        self.asked_at: dict[str, float] = {}
        """lane -> step time at which its newest adopted plan was asked for (its age)."""

    # --- the policy's side ------------------------------------------------------------------------
    def busy(self, lane: str) -> bool:
        """Whether ``lane`` has a job asked for and not adopted yet."""
        return any(j.lane == lane for j in self.pending.values())

    def submit(self, lane: str, fn: Callable[[], Any], on_done: Callable[[Any], None]) -> int:
        """Ask for ``fn()`` (a pure function of a snapshot); ``on_done(result)`` adopts it on the control thread."""
        if self.busy(lane):
            raise RuntimeError(f"planner lane {lane!r} already has a job in flight")
        job = _Job(self.tickets, lane, fn, on_done, self.step, self.t)
        self.tickets += 1
        self.pending[job.ticket] = job
        self._start(job)
        return job.ticket

    def _start(self, job: _Job) -> None:
        job.run()
        self._adopt(job)

    # --- the step's side --------------------------------------------------------------------------
    def begin(self, step: int, t: float, script: Iterable[int] | None = None) -> None:
        """A step begins: adopt the jobs that are due by this runner's rule (``script``: the replay's)."""
        self.step, self.t = step, t
        self.adopted_now = []
        for job in self._due(script):
            self._adopt(job)

    def _due(self, script) -> list[_Job]:
        return []

    def _adopt(self, job: _Job) -> None:
        del self.pending[job.ticket]
        self.adopted_now.append(job.ticket)
        self.adopted += 1
        self.times_ms.append(job.ms)
        self.waits.append(self.t - job.t)
        self.asked_at[job.lane] = job.t
        if job.error is not None:
            raise job.error
        job.on_done(job.result)

    def close(self) -> None:
        """No more jobs (the worker, where there is one, ends after the one it runs)."""

    # --- what the report and the live view show ---------------------------------------------------------
    def stats(self, t: float | None = None) -> dict:
        """Plans asked for and adopted, their compute times [ms] (p50, p99, max), the most step time from asking to
        driving [s], the age of the newest plan adopted [s] (``t``: now, default the step's) and how long the job in
        flight has been running [s]."""
        t = self.t if t is None else t
        ts = sorted(self.times_ms)
        def q(p: float) -> float | None:
            return round(ts[min(len(ts) - 1, int(math.ceil(p * len(ts))) - 1)], 3) if ts else None
        age = t - max(self.asked_at.values()) if self.asked_at else None
        flight = [t - j.t for j in self.pending.values()]
        return {"mode": self.mode, "asked": self.tickets, "adopted": self.adopted, "ms_p50": q(0.5), "ms_p99": q(0.99),
                "ms_max": round(ts[-1], 3) if ts else None, "wait_max_s": round(max(self.waits), 3) if self.waits else None,
                "age_s": None if age is None else round(age, 3), "in_flight_s": round(max(flight), 3) if flight else None}


class ThreadRunner(PlanRunner):
    """Jobs on one worker thread, in the order asked. ``lockstep_steps``: None, real time (adopted at the first
    step after it finished); n >= 1, lock-step (adopted at the asking step + n, waited for there)."""

    def __init__(self, lockstep_steps: int | None = None) -> None:
        super().__init__()
        if lockstep_steps is not None and lockstep_steps < 1:
            raise ValueError(f"lockstep_steps must be >= 1, not {lockstep_steps}")
        self.lockstep_steps = lockstep_steps
        self.mode = "real time" if lockstep_steps is None else f"lock-step +{lockstep_steps}"
        self._q: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def _start(self, job: _Job) -> None:
        if self._thread is None:
            sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
            self._thread = threading.Thread(target=self._work, name="planner", daemon=True)
            self._thread.start()
        self._q.put(job)

    def _work(self) -> None:
        while (job := self._q.get()) is not None:
            job.run()

    def _due(self, script) -> list[_Job]:
        jobs = sorted(self.pending.values(), key=lambda j: j.ticket)
        if self.lockstep_steps is None:
            return [j for j in jobs if j.done.is_set()]
        due = [j for j in jobs if j.step + self.lockstep_steps <= self.step]
        for j in due:
            if not j.done.wait(WAIT_WARN_S):
                log.warning("plan %d (%s, asked at step %d) still computing at step %d: the step waits for it "
                            "(lock-step)", j.ticket, j.lane, j.step, self.step)
                j.done.wait()
        return due

    def close(self) -> None:
        if self._thread is not None:
            self._q.put(None)


class ScriptedRunner(PlanRunner):
    """Replay: a job waits until a step's ``script`` names its ticket, and is computed then. A step without a
    script (a log from before the runners) adopts every job at once, as the inline runner did."""

    mode = "scripted"

    def __init__(self) -> None:
        super().__init__()
        self._scripted = True

    def begin(self, step: int, t: float, script: Iterable[int] | None = None) -> None:
        self._scripted = script is not None
        super().begin(step, t, script)

    def _start(self, job: _Job) -> None:
        if not self._scripted:
            super()._start(job)

    def _due(self, script) -> list[_Job]:
        due = [self.pending[k] for k in (script or ()) if k in self.pending]
        for j in due:
            j.run()
        return due


__all__ = ["PlanRunner", "ScriptedRunner", "ThreadRunner", "SWITCH_INTERVAL_S"]
