"""The clock of a Zenoh router's host against ours, from the timestamps the router puts on what it routes.

A router with timestamping on (zenoh's default for routers) stamps every sample that reaches it without a
timestamp with its hybrid logical clock, which follows its host's wall clock (NTP64, UNIX epoch). A probe
sent by one of our sessions at t0 and received by another through the router at t1 (our wall clock), stamped
tr by the router on the way, gives the router host's clock minus ours as tr - (t0 + t1) / 2, within
(t1 - t0) / 2: the router stamped it somewhere in between (the NTP bound). The probe with the shortest round
trip is kept. Without timestamps on what arrives (the router's timestamping off) nothing is measured.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import zenoh

from .session import SessionConfig, SessionError, open_session


@dataclass(frozen=True)
class ClockOffset:
    offset_s: float
    """The router host's clock minus ours [s]."""
    bound_s: float
    """|error| <= this [s]: half the round trip of the probe it came from."""
    probes: int
    """Probes that came back stamped."""


def router_offset(session: zenoh.Session, cfg: SessionConfig, key: str, probes: int = 8,
                  timeout_s: float = 2.0) -> ClockOffset | str:
    """Probes put on ``key`` from ``session``, received through the router by a second session opened with ``cfg``;
    a :class:`ClockOffset`, or why there is none (one line)."""
    got: list[tuple[float, float, float]] = []  # (t0, tr, t1)
    unstamped = [0]
    cv = threading.Condition()

    def on_probe(sample: zenoh.Sample) -> None:
        t1 = time.time()
        try:
            t0 = float(sample.payload.to_bytes())
        except ValueError:  # not one of our probes
            return
        with cv:
            if sample.timestamp is None:
                unstamped[0] += 1
            else:
                got.append((t0, sample.timestamp.get_time_as_ntp64().as_secs_f64(), t1))
            cv.notify_all()

    try:
        rx = open_session(cfg)
    except SessionError as e:
        return f"not measured: a second session could not open: {e}"
    with rx:
        sub = rx.declare_subscriber(key, on_probe)
        try:
            _send(session, key, probes, timeout_s, cv, lambda: len(got) + unstamped[0])
        finally:
            sub.undeclare()
    with cv:
        stamped, bare = list(got), unstamped[0]
    if not stamped:
        if bare:
            return "not measured: the router does not timestamp what it routes (its timestamping is off)"
        return f"not measured: no probe came back through the router within {timeout_s:g} s (access control on {key}?)"
    t0, tr, t1 = min(stamped, key=lambda g: g[2] - g[0])
    return ClockOffset(offset_s=tr - (t0 + t1) / 2, bound_s=(t1 - t0) / 2, probes=len(stamped))


def _send(session: zenoh.Session, key: str, probes: int, timeout_s: float, cv: threading.Condition, heard) -> None:
    """A probe every 20 ms (the first ones may go before the router knows our subscriber) until ``probes`` came back."""
    pub = session.declare_publisher(key)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            pub.put(repr(time.time()).encode())
            with cv:
                if cv.wait_for(lambda: heard() >= probes, timeout=0.02):
                    return
    finally:
        pub.undeclare()
