"""The Driver base keeps the rules for every backend: clamp (eq. 2), the supervisor (watchdog,
keep-alives, health), the fault latch, counters and liveness, zero on close.

The supervisor is stepped by hand with fake clocks (``supervise_once``): the driver's clock and
the wall clock each move only when the test moves them, so nothing here waits for a timer.
"""

from __future__ import annotations

import math

import pytest

from conftest import wait_for
from stack.drivers import BACKENDS, DriverError, DriverLimits, UnknownDriver, driver_class
from stack.drivers.base import Driver, Keepalive, Odometry, Periodic
from stack.drivers.testing import FakeClock

LIMITS = DriverLimits(1.0, 1.0, cmd_timeout=0.5)


class Recorder(Driver):
    """A backend that records what reaches its wire (the base class is under test, not this).

    ``keepalive``: resend the last command this often; ``beat``: a heartbeat of its own this often,
    also after a fault; ``stale_after``: the ``device`` stream older than this is a fault."""

    name = "recorder"

    def __init__(self, *a, keepalive: float | None = None, beat: float | None = None,
                 stale_after: float | None = None, **kw):
        super().__init__(*a, **kw)
        self.wire: list[tuple[float, float]] = []
        self.beats = 0
        self.opened = 0
        self.closed = False
        self.fail_sends = False
        self._keepalive, self._beat, self._stale_after = keepalive, beat, stale_after

    def _open(self):
        self.opened += 1
        self._alive("device")

    def _send(self, v, w):
        if self.fail_sends:
            raise DriverError("recorder: the wire is cut")
        self.wire.append((v, w))

    def _read(self):
        return Odometry(0.0, 0.0, 0.0)

    def _close(self):
        self.closed = True

    def _keepalives(self):
        out = []
        if self._keepalive is not None:
            out.append(Keepalive("command", self._keepalive))
        if self._beat is not None:
            out.append(Keepalive("beat", self._beat, self._send_beat, faulted=True))
        return out

    def _send_beat(self):
        self.beats += 1

    def _health(self, now):
        age = self.age("device", now)
        if self._stale_after is not None and age is not None and age > self._stale_after:
            return f"device silent for {age:.2f} s"
        return None


def fake(**kw) -> tuple[Recorder, FakeClock, FakeClock]:
    clock, wall = FakeClock(), FakeClock()
    return Recorder(1, kw.pop("limits", LIMITS), clock=clock, wall=wall, **kw), clock, wall


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
    with pytest.raises(DriverError, match="recorder driver 1: command on a closed driver"):
        d.command(0.1, 0.0)
    d.close()  # twice: nothing more on the wire
    assert d.wire[-1] == (0.0, 0.0) and len(d.wire) == 2


def test_exception_inside_block_still_zeroes():
    d = Recorder(1, DriverLimits(1.0, 1.0))
    with pytest.raises(RuntimeError):
        with d:
            d.command(0.9, 0.0)
            raise RuntimeError("policy blew up")
    assert d.wire[-1] == (0.0, 0.0)


def test_close_finishes_when_the_zero_cannot_be_sent():
    d = Recorder(1, LIMITS).open()
    d.command(0.5, 0.0)
    d.fail_sends = True
    d.close()  # logged, not raised: the device is released all the same
    assert d.closed and d.wire == [(0.5, 0.0)]


def test_watchdog_zeroes_a_stale_command_once():
    d, clock, wall = fake()
    with d:
        d.command(0.8, 0.0)
        clock.run(d, 0.5, 0.125, wall)  # exactly cmd_timeout old: not yet
        assert d.wire == [(0.8, 0.0)] and d.watchdog_trips == 0
        clock.run(d, 0.125, 0.125, wall)
        assert d.wire == [(0.8, 0.0), (0.0, 0.0)] and d.watchdog_trips == 1 == d.counters["watchdog_trips"]
        clock.run(d, 2.0, 0.125, wall)
        assert len(d.wire) == 2 and d.last_sent == (0.0, 0.0)  # trips once, does not spam zeros
        assert d.command(0.5, 0.0) == (0.5, 0.0) and d.wire[-1] == (0.5, 0.0)
        assert d.fault is None  # a stale command is not a device fault


def test_watchdog_follows_the_drivers_clock_not_the_wall():
    d, clock, wall = fake()
    with d:
        d.command(0.8, 0.0)
        wall.advance(10.0)  # lock-step: the wall runs, sim time stands while the world waits
        d.supervise_once()
        assert d.wire[-1] == (0.8, 0.0)
        clock.advance(0.75)
        d.supervise_once()
        assert d.wire[-1] == (0.0, 0.0)


def test_the_supervise_thread_runs_the_watchdog_on_real_clocks():
    with Recorder(1, DriverLimits(1.0, 1.0, cmd_timeout=0.05)) as d:
        d.command(0.8, 0.0)
        assert wait_for(lambda: d.watchdog_trips == 1, 2.0)
        assert d.wire[-1] == (0.0, 0.0)


def test_keepalive_resends_the_last_command_at_its_period():
    d, clock, wall = fake(keepalive=0.25)
    with d:
        assert d.wire == [(0.0, 0.0)]  # the first one at once, when armed
        clock.run(d, 0.25, 0.125, wall)  # a period later: the last command (zero) again
        assert d.wire == [(0.0, 0.0)] * 2
        d.command(0.5, 0.25)
        clock.run(d, 0.125, 0.125, wall)
        d.command(0.5, 0.25)  # every command restarts the period
        clock.run(d, 0.125, 0.125, wall)
        assert d.wire[2:] == [(0.5, 0.25), (0.5, 0.25)]
        clock.run(d, 0.25, 0.125, wall)
        assert d.wire[2:] == [(0.5, 0.25)] * 3
        clock.run(d, 0.25, 0.125, wall)  # once more; then the watchdog (0.5 s after the command) zeroes
        assert d.wire[5:] == [(0.5, 0.25), (0.0, 0.0)] and d.watchdog_trips == 1
        clock.run(d, 0.25, 0.125, wall)  # and the keepalive resends the zero
        assert d.wire[5:] == [(0.5, 0.25), (0.0, 0.0), (0.0, 0.0)]


@pytest.mark.parametrize("moving", ["driver clock", "wall clock"])
def test_keepalive_is_due_by_either_clock(moving):
    """``Periodic``: sim time that stands still (the world waits) or runs ahead of the wall (it steps
    fast) must not starve or flood the device; whichever clock has the period passed sends."""
    d, clock, wall = fake(limits=DriverLimits(1.0, 1.0, cmd_timeout=100.0), keepalive=0.25)
    ticking = clock if moving == "driver clock" else wall
    with d:
        d.command(0.3, 0.0)
        for _ in range(8):  # 1 s on one clock, none on the other
            ticking.advance(0.125)
            d.supervise_once()
        assert d.wire == [(0.0, 0.0)] + [(0.3, 0.0)] * 5


def test_periodic_by_hand():
    p = Periodic(0.5)
    assert p.due(0.0, 0.0)  # never sent: due at once
    p.done(10.0, 100.0)
    assert not p.due(10.25, 100.25) and p.due(10.5, 100.0) and p.due(10.0, 100.5)


def test_stale_device_trips_the_fault_latch():
    d, clock, wall = fake(keepalive=0.25, beat=0.5, stale_after=0.3)
    with d:
        d.command(0.6, 0.0)
        clock.run(d, 0.25, 0.125, wall)
        assert d.fault is None and d.liveness() == {"device": 0.25}
        clock.run(d, 0.125, 0.125, wall)
        assert d.fault == "device silent for 0.38 s"  # the first reason, one line
        assert d.wire[-1] == (0.0, 0.0) and d.last_sent == (0.0, 0.0)
        n, beats = len(d.wire), d.beats
        d._trip("a second fault")  # the first reason is kept; no second zero
        assert d.fault == "device silent for 0.38 s" and len(d.wire) == n
        assert d.command(0.5, 0.5) == (0.0, 0.0)  # motion refused
        clock.run(d, 1.0, 0.125, wall)
        assert d.wire[n:] == [(0.0, 0.0)]  # the command's zero only: the command keep-alive stops
        assert d.beats == beats + 2  # a keep-alive marked ``faulted`` goes on
        d._alive("device")  # the device speaks again: still faulted until close/open
        assert d.command(0.5, 0.5) == (0.0, 0.0) and d.fault
    assert d.wire[-1] == (0.0, 0.0)
    with d:
        assert d.fault is None and d.opened == 2
        assert d.command(0.5, 0.5) == (0.5, 0.5)


def test_the_control_step_itself_checks_health():
    """A starved supervisor thread must not delay a fault: ``command()`` checks on the driver's clock."""
    d, clock, _ = fake(stale_after=0.3)
    with d:
        clock.advance(0.25)
        assert d.command(0.4, 0.0) == (0.4, 0.0)
        clock.advance(0.125)
        assert d.command(0.4, 0.0) == (0.0, 0.0) and d.fault == "device silent for 0.38 s"


def test_no_supervision_before_open_or_after_close():
    d, clock, wall = fake(keepalive=0.125, stale_after=0.1)
    clock.run(d, 1.0, 0.125, wall)
    assert d.wire == [] and d.fault is None
    with d:
        d.command(0.2, 0.0)
    clock.run(d, 1.0, 0.125, wall)
    assert d.wire == [(0.0, 0.0), (0.2, 0.0), (0.0, 0.0)] and d.fault is None


def test_a_failing_keepalive_is_counted_and_logged():
    d, clock, wall = fake(keepalive=0.25)
    with d:
        d.command(0.2, 0.0)
        d.fail_sends = True
        clock.run(d, 0.5, 0.125, wall)
        assert d.counters["tx_error"] == 2 and d.fault is None  # this backend only logs it
        d.fail_sends = False


def test_counters_and_malformed_reports():
    told: list[str] = []
    d = Recorder(1, LIMITS, on_malformed=told.append)
    d.count("tx")
    d.count("tx")
    d.count("bad_crc", malformed=True)
    assert d.counters == {"tx": 2, "bad_crc": 1} and told == ["recorder/bad_crc"]


def test_liveness_is_per_stream_on_the_drivers_clock():
    d, clock, _ = fake()
    with d:
        clock.advance(1.0)
        d._alive("odom")
        clock.advance(0.5)
        assert d.liveness() == {"device": 1.5, "odom": 0.5}
        assert d.age("odom") == 0.5 and d.age("scan") is None
    d.open()
    assert d.liveness() == {"device": 0.0}  # opening forgets the old streams
    d.close()


def test_faulted_driver_sends_zero():
    with Recorder(1, DriverLimits(1.0, 1.0)) as d:
        d.fault = "axis error"
        assert d.command(0.5, 0.5) == (0.0, 0.0)


def test_backends_keep_their_config_class_and_supervise_on_the_base():
    for name in ("can", "mavlink", "jackal"):
        cls = driver_class(name)
        assert cls.config_class is not None and cls.config_class.__name__.lower().startswith(name)
        assert cls._health is not Driver._health and cls._keepalives is not Driver._keepalives
        for own in ("_supervise", "_trip", "_watchdog", "count", "supervise_once"):
            assert getattr(cls, own) is getattr(Driver, own), (name, own)


def test_registry_is_lazy_and_names_unknown():
    assert "sim" in BACKENDS
    assert driver_class("sim").name == "sim"
    with pytest.raises(UnknownDriver, match="driver 'warp' is not available"):
        driver_class("warp")
