"""cProfile in every thread of a fleet's world and agent processes (``bench/profile_step.py --cprofile``).

On ``PYTHONPATH`` with ``STACK_CPROFILE_DIR`` set, a process started as ``-m stack.agents`` or
``-m stack.sim_bridge`` profiles (on each thread's CPU clock) its main thread and every thread it starts (zenoh-python's callback
threads are ``threading`` threads) and writes ``<dir>/<kind>-<pid>.prof`` (pstats, all threads merged)
when it exits.
"""

import atexit
import cProfile
import os
import sys
import threading
import time

_DIR = os.environ.get("STACK_CPROFILE_DIR")
_ARGV = " ".join(getattr(sys, "orig_argv", sys.argv))
_KIND = "agent" if "stack.agents" in _ARGV else "world" if "stack.sim_bridge" in _ARGV else None

if _DIR and _KIND:
    _profiles: list[cProfile.Profile] = []

    def _thread_start(frame, event, arg):  # the first event of each new thread: profile it from here on
        sys.setprofile(None)
        pr = cProfile.Profile(time.thread_time)  # CPU time of the thread: waits cost nothing
        _profiles.append(pr)
        pr.enable()

    def _dump() -> None:
        import pstats

        for pr in _profiles:
            pr.disable()
        stats = None
        for pr in _profiles:
            try:
                stats = pstats.Stats(pr) if stats is None else stats.add(pr)
            except TypeError:  # a profiler that never recorded anything
                continue
        if stats is not None:
            stats.dump_stats(os.path.join(_DIR, f"{_KIND}-{os.getpid()}.prof"))

    _main = cProfile.Profile(time.thread_time)
    _profiles.append(_main)
    threading.setprofile(_thread_start)
    atexit.register(_dump)
    _main.enable()
