"""The Driver base keeps the rules for every backend: clamp (eq. 2), watchdog, zero on close."""

from __future__ import annotations

import math
import time

import pytest

from stack.drivers import BACKENDS, DriverError, DriverLimits, UnknownDriver, driver_class
from stack.drivers.base import Driver, Odometry


class Recorder(Driver):
    """A backend that records what reaches its wire (the base class is under test, not this)."""

    name = "recorder"

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.wire: list[tuple[float, float]] = []
        self.closed = False

    def _open(self):
        pass

    def _send(self, v, w):
        self.wire.append((v, w))

    def _read(self):
        return Odometry(0.0, 0.0, 0.0)

    def _close(self):
        self.closed = True


def test_clamps_to_limits_and_rejects_nan():
    with Recorder(1, DriverLimits(v_max=1.0, w_max=0.5)) as d:
        assert d.command(3.0, -2.0) == (1.0, -0.5)
        assert d.command(-5.0, 0.2) == (-1.0, 0.2)
        assert d.command(math.nan, 0.3) == (0.0, 0.0)
        assert d.command(0.5, math.inf) == (0.0, 0.0)
    assert d.wire[:4] == [(1.0, -0.5), (-1.0, 0.2), (0.0, 0.0), (0.0, 0.0)]


def test_context_exit_sends_zero_then_closes():
    d = Recorder(1, DriverLimits(1.0, 1.0))
    with d:
        d.command(0.7, 0.1)
    assert d.wire[-1] == (0.0, 0.0) and d.closed
    with pytest.raises(DriverError):
        d.command(0.1, 0.0)


def test_exception_inside_block_still_zeroes():
    d = Recorder(1, DriverLimits(1.0, 1.0))
    with pytest.raises(RuntimeError):
        with d:
            d.command(0.9, 0.0)
            raise RuntimeError("policy blew up")
    assert d.wire[-1] == (0.0, 0.0)


def test_watchdog_zeroes_a_stale_command():
    d = Recorder(1, DriverLimits(1.0, 1.0, cmd_timeout=0.1))
    with d:
        d.command(0.8, 0.0)
        time.sleep(0.4)
        assert d.wire[-1] == (0.0, 0.0)
        assert d.watchdog_trips == 1
        n = len(d.wire)
        time.sleep(0.2)
        assert len(d.wire) == n  # trips once, does not spam zeros
        d.command(0.5, 0.0)
        assert d.wire[-1] == (0.5, 0.0)


def test_watchdog_follows_the_given_clock():
    now = {"t": 0.0}
    d = Recorder(1, DriverLimits(1.0, 1.0, cmd_timeout=0.5), clock=lambda: now["t"])
    with d:
        d.command(0.8, 0.0)
        time.sleep(0.2)  # wall time passes, sim time does not: no trip
        assert d.wire[-1] == (0.8, 0.0)
        now["t"] = 1.0
        time.sleep(0.2)
        assert d.wire[-1] == (0.0, 0.0)


def test_faulted_driver_sends_zero():
    with Recorder(1, DriverLimits(1.0, 1.0)) as d:
        d.fault = "axis error"
        assert d.command(0.5, 0.5) == (0.0, 0.0)


def test_registry_is_lazy_and_names_unknown():
    assert "sim" in BACKENDS
    assert driver_class("sim").name == "sim"
    with pytest.raises(UnknownDriver, match="driver 'warp' is not available"):
        driver_class("warp")
