"""What the orchestrator hears on Zenoh during a run: the world's clock, status and fault requests,
the agents' diag, state and liveliness."""

from __future__ import annotations

import threading
import time

import zenoh

from ..comm import Keys, receive
from ..comm.messages import Clock, Diag, FaultRequest, State, WorldStatus


class Monitor:
    """Subscribers on our session; every field under ``lock``."""

    def __init__(self, session: zenoh.Session, keys: Keys):
        self.lock = threading.Lock()
        self.t = 0.0
        self.step = 0
        self.status = "starting"
        self.why = ""
        self.diag: dict[int, Diag] = {}
        self.estimates: dict[int, list[tuple[int, float, float]]] = {}
        self.situation: dict[int, str] = {}
        self.alive: set[int] = set()
        self.malformed = 0
        self.fault_requests: list[FaultRequest] = []
        self._subs = [
            session.declare_subscriber(keys.world("fault"), self._on(FaultRequest, self.fault_requests.append)),
            session.declare_subscriber(keys.world("clock"), self._on(Clock, self._clock)),
            session.declare_subscriber(keys.world("status"), self._on(WorldStatus, self._status)),
            session.declare_subscriber(keys.all_robots("diag"), self._on(Diag, self._diag)),
            session.declare_subscriber(keys.all_robots("state"), self._on(State, self._state)),
            session.liveliness().declare_subscriber(keys.all_alive, self._alive, history=True),
        ]

    def _alive(self, sample: zenoh.Sample) -> None:
        rid = Keys.id_of(str(sample.key_expr))
        if rid is None:
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self.alive.discard(rid)
            else:
                self.alive.add(rid)

    def wait_alive(self, ids: set[int], timeout: float) -> set[int]:
        """Wait until every id has a liveliness token; returns the ones still missing."""
        deadline = time.monotonic() + timeout
        while True:
            with self.lock:
                missing = ids - self.alive
            if not missing or time.monotonic() > deadline:
                return missing
            time.sleep(0.1)

    def _on(self, kind, handler):
        def callback(sample: zenoh.Sample) -> None:
            m = receive(sample, kind, self._bad)
            if m is not None:
                with self.lock:
                    handler(m)
        return callback

    def _bad(self, _key: str) -> None:
        with self.lock:
            self.malformed += 1

    def _clock(self, m: Clock) -> None:
        self.t, self.step = m.t, m.step

    def _status(self, m: WorldStatus) -> None:
        self.status, self.why = m.state, m.why

    def _diag(self, m: Diag) -> None:
        old = self.diag.get(m.id)
        if old is None or m.step >= old.step or m.state == "stopped":
            self.diag[m.id] = m

    def _state(self, m: State) -> None:
        self.estimates.setdefault(m.id, []).append((m.step, m.x, m.y))
        if m.situation:
            self.situation[m.id] = m.situation

    def take(self) -> tuple[float, str, list[FaultRequest]]:
        """(sim time, world status, the fault requests since the last take)."""
        with self.lock:
            requests, self.fault_requests[:] = list(self.fault_requests), []
            return self.t, self.status, requests

    def results(self) -> tuple[dict[int, Diag], dict[int, list[tuple[int, float, float]]]]:
        """(each agent's last diag, each agent's published (step, x, y) estimates)."""
        with self.lock:
            return dict(self.diag), {k: list(v) for k, v in self.estimates.items()}

    def close(self) -> None:
        """Undeclare the subscribers (once)."""
        subs, self._subs = self._subs, []
        for sub in subs:
            sub.undeclare()
