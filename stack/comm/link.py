"""Whether this process's Zenoh session has its router(s): "I lost my network" apart from "a peer left".

A client that loses its router sees every remote liveliness token go away at once (zenoh deletes what it can no
longer vouch for), exactly as if every peer had died. :class:`LinkWatch` tells the two apart: it polls the session's
routers (``session.info.routers_zid()``, from the caller's own thread, never from a zenoh callback) and keeps the
outages it saw. A token that went away is a peer gone only when the link was up from before it went until
``confirm_s`` after (:class:`GoneJudge`); one that went away with the link is our loss, and the peer is kept.

    watch = LinkWatch(session)
    judge = GoneJudge(watch)
    judge.deleted(rid)           # liveliness DELETE (a callback: only notes it)
    watch.poll(); judge.confirmed()   # each tick: the peers really gone
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import zenoh


REJOIN_S = 3.0
"""[s] after our link is back: how long a robot's token may take to come back before it counts as gone."""

CONFIRM_S = 0.5
"""[s] how long a token must have been gone, with our link up all along, before its robot counts as gone."""


@dataclass
class Outage:
    """One stretch of time this session had no router (``end`` None: still on)."""

    start: float
    end: float | None = None

    def as_dict(self, to_run=lambda t: t) -> dict:
        return {"start": round(to_run(self.start), 3), "end": None if self.end is None else round(to_run(self.end), 3)}


@dataclass
class LinkWatch:
    """This session's link to its router(s), polled (``poll``) on the caller's clock (``clock``, monotonic)."""

    session: zenoh.Session
    clock: object = time.monotonic
    up: bool = True
    outages: list[Outage] = field(default_factory=list)
    changed_at: float = -math.inf  # clock time of the newest change (lost or back)

    def poll(self) -> str | None:
        """Look once: ``"lost"`` or ``"back"`` where the link changed since the last poll, else None."""
        try:
            now_up = len(self.session.info.routers_zid()) > 0
        except zenoh.ZError:  # a closing session
            now_up = False
        if now_up == self.up:
            return None
        t = self.clock()
        self.up, self.changed_at = now_up, t
        if not now_up:
            self.outages.append(Outage(t))
            return "lost"
        if self.outages and self.outages[-1].end is None:
            self.outages[-1].end = t
        return "back"

    @property
    def lost_since(self) -> float | None:
        """When the outage now on began (None: the link is up)."""
        return None if self.up or not self.outages else self.outages[-1].start


class GoneJudge:
    """Liveliness DELETEs held until the link says whose loss they were (thread-safe: callbacks note, a tick judges).

    After an outage, the tokens come back as the session rejoins; a robot whose token is not back ``rejoin_s``
    after the link is (it died while we could not hear) is gone then."""

    def __init__(self, watch: LinkWatch, confirm_s: float = CONFIRM_S, rejoin_s: float = REJOIN_S):
        self.watch, self.confirm_s, self.rejoin_s = watch, confirm_s, rejoin_s
        self._lock = threading.Lock()
        self._pending: dict[int, float] = {}  # robot id -> when its token went away (watch clock)
        self.present: set[int] = set()  # robots whose token we hold now
        self.known: set[int] = set()  # robots whose token we ever held
        self._rejoin_due: float | None = None
        self._seen_change = watch.changed_at
        self.discarded = 0  # tokens that went away with our own link (their robots kept)

    def deleted(self, rid: int) -> None:
        with self._lock:
            self.present.discard(rid)
            self._pending.setdefault(rid, self.watch.clock())

    def returned(self, rid: int) -> None:
        with self._lock:
            self._pending.pop(rid, None)
            self.present.add(rid)
            self.known.add(rid)

    def confirmed(self) -> list[int]:
        """Robots whose token went away ``confirm_s`` ago while the link stayed up (call after ``poll``), and those
        not back ``rejoin_s`` after an outage: gone. A token that went while the link was down, or before it went
        down, is dropped from the list (our loss, not theirs)."""
        w, now = self.watch, self.watch.clock()
        out = set()
        with self._lock:
            if w.changed_at != self._seen_change:
                self._seen_change = w.changed_at
                self._rejoin_due = w.changed_at + self.rejoin_s if w.up else None
            for rid, t in list(self._pending.items()):
                if not w.up or w.changed_at >= t:  # went with our link (or during its outage): ours, not theirs
                    del self._pending[rid]
                    self.discarded += 1
                elif now - t >= self.confirm_s:
                    del self._pending[rid]
                    out.add(rid)
            if self._rejoin_due is not None and w.up and now >= self._rejoin_due:
                self._rejoin_due = None
                out |= self.known - self.present - set(self._pending)
        return sorted(out)
