"""Memory of running processes from ``/proc/<pid>/smaps_rollup`` (Linux): RSS, PSS and USS in MB.

RSS counts every shared page in full (numpy's, zenoh's and libpython's pages once per process),
USS only the pages no other process maps, PSS each shared page divided among the processes that
map it: the sum of PSS over a fleet is what the fleet costs, so PSS is the fair per-agent figure.

:class:`Sampler` wraps a fleet's ``spawn`` (``stack.fleet.orchestrator.Fleet``) and samples every
process it started while the fleet runs, keeping each one's peak and the shared libraries it mapped.
"""

from __future__ import annotations

import threading
from pathlib import Path

FIELDS = {"Rss:": "rss", "Pss:": "pss", "Private_Clean:": "uss", "Private_Dirty:": "uss"}


def memory_mb(pid: int) -> dict[str, float] | None:
    """{'rss', 'pss', 'uss'} of process ``pid`` in MB (2**20 bytes); None when it is gone or unreadable."""
    out = {"rss": 0.0, "pss": 0.0, "uss": 0.0}
    try:
        text = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        parts = line.split()
        if parts and parts[0] in FIELDS:
            out[FIELDS[parts[0]]] += int(parts[1]) / 1024  # kB
    return out


def libraries(pid: int) -> set[str]:
    """The file names of the shared objects process ``pid`` maps (empty when it is gone)."""
    try:
        text = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return set()
    return {Path(line.split()[-1]).name for line in text.splitlines() if ".so" in line.rsplit("/", 1)[-1]}


class Sampler:
    """``spawn`` for a Fleet that remembers each process; a thread samples them every ``period_s``.

    ``peaks()``: name -> the largest rss, pss and uss seen (each its own maximum); ``libs`` (with ``libs=True``): name ->
    every shared object seen mapped."""

    def __init__(self, spawn, period_s: float = 0.5, libs: bool = False):
        self._spawn, self.period_s, self._libs = spawn, period_s, libs
        self.procs: dict[str, object] = {}
        self._peak: dict[str, dict[str, float]] = {}
        self.libs: dict[str, set[str]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __call__(self, name, argv, log_path, env):
        proc = self._spawn(name, argv, log_path, env)
        self.procs[name] = proc
        return proc

    def __enter__(self) -> Sampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            for name, proc in list(self.procs.items()):
                m = memory_mb(proc.p.pid)
                if m is None:
                    continue
                peak = self._peak.setdefault(name, dict(m))
                for k, v in m.items():
                    peak[k] = max(peak[k], v)
                if self._libs:
                    self.libs.setdefault(name, set()).update(libraries(proc.p.pid))

    def peaks(self) -> dict[str, dict[str, float]]:
        return {name: dict(m) for name, m in self._peak.items()}
