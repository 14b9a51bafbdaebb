"""A clock that a test moves by hand, for stepping a driver's supervision deterministically.

>>> clock, wall = FakeClock(), FakeClock()
>>> drv = MyDriver(1, DriverLimits(1.0, 1.0), clock=clock, wall=wall)   # doctest: +SKIP
>>> clock.run(drv, 0.5, 0.125, wall)   # four supervision rounds, both clocks moving   # doctest: +SKIP

With both clocks fake the driver's own supervise thread only ever sees times the test set,
so whatever it does the test's ``supervise_once`` would have done at the same time: the
outcome does not depend on which thread got there first. Pick periods and steps exact in
binary (0.125, 1/64) where a test counts keep-alives, so sums of steps land on them.

``settle`` waits for a device that was just silenced: until what is already on the way has
arrived (a counter stops changing), so a stale-device test can then age the silence by hand.
"""

from __future__ import annotations

import threading
import time
from typing import Callable


class FakeClock:
    """``clock()`` is the time; ``advance(dt)`` moves it; ``run`` steps a driver's supervision."""

    def __init__(self, t: float = 0.0):
        self.t = t
        self._lock = threading.Lock()

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        with self._lock:
            self.t += dt
            return self.t

    def run(self, driver, seconds: float, dt: float, *others: "FakeClock") -> None:
        """Advance this clock (and ``others``) by ``dt`` at a time for ``seconds``, one
        ``driver.supervise_once()`` after each step."""
        for _ in range(round(seconds / dt)):
            for c in (self, *others):
                c.advance(dt)
            driver.supervise_once()


def settle(value: Callable[[], object], quiet: float = 0.1, timeout: float = 3.0) -> bool:
    """Until ``value()`` (a message counter) has not changed for ``quiet`` s of wall time; False after ``timeout``."""
    end = time.monotonic() + timeout
    last, since = value(), time.monotonic()
    while time.monotonic() < end:
        time.sleep(quiet / 10)
        now = value()
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet:
            return True
    return False


__all__ = ["FakeClock", "settle"]
