"""The radio model, applied at the receiving agent, per message and per sender.

A message from robot j reaches robot i when

1. the sender's *reported* position (in its state) is within ``comm_range`` of the
   receiver's *own estimate* of its position (ground truth is never used),
2. it survives loss: Bernoulli with probability ``loss``, or a Gilbert-Elliott two-state
   channel (good/bad, transition probabilities ``p_good_bad``/``p_bad_good``, loss
   ``loss_good``/``loss_bad`` per state) when ``burst`` is set,
3. after its latency: ``latency_ms`` plus a uniform jitter in ``[0, jitter_ms]``, counted
   from the sender's stamp on the receiver's clock (sim time in lock-step).

Every draw comes from a generator seeded by (seed, receiver, sender), so a run is
reproducible whatever the order in which senders' messages interleave.
"""

from __future__ import annotations

import heapq
import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class RadioConfig:
    comm_range: float = 10.0
    loss: float = 0.0
    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    burst: tuple[float, float, float, float] | None = None  # p_good_bad, p_bad_good, loss_good, loss_bad
    seed: int = 0


@dataclass
class RadioCounters:
    received: int = 0  # messages offered to the model (arrived on the wire and decoded)
    delivered: int = 0
    dropped_loss: int = 0
    dropped_range: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(received=self.received, delivered=self.delivered, dropped_loss=self.dropped_loss, dropped_range=self.dropped_range)


class _Channel:
    """One sender -> this receiver: its own random stream and burst state."""

    def __init__(self, seed: int, receiver: int, sender: int, burst_start_bad: bool = False):
        self.rng = np.random.default_rng([seed, receiver, sender])
        self.bad = burst_start_bad


class RadioModel:
    """Decides delivery of neighbours' messages for one receiving robot."""

    def __init__(self, cfg: RadioConfig, receiver_id: int):
        self.cfg = cfg
        self.receiver_id = receiver_id
        self.counters = RadioCounters()
        self.by_sender: dict[int, RadioCounters] = {}  # the same counters per sender: the comm graph's links
        self._channels: dict[int, _Channel] = {}
        self._queue: list[tuple[float, int, int, Any]] = []
        self._tie = itertools.count()

    def _channel(self, sender: int) -> _Channel:
        ch = self._channels.get(sender)
        if ch is None:
            ch = self._channels[sender] = _Channel(self.cfg.seed, self.receiver_id, sender)
        return ch

    def lost(self, sender: int) -> bool:
        """One loss draw on the sender's channel (advances the burst chain once per message)."""
        ch = self._channel(sender)
        if self.cfg.burst is None:
            return bool(ch.rng.random() < self.cfg.loss) if self.cfg.loss > 0 else False
        p_gb, p_bg, loss_good, loss_bad = self.cfg.burst
        # Gilbert-Elliott: state transition, then a loss draw with the state's loss rate
        if ch.bad:
            ch.bad = not (ch.rng.random() < p_bg)
        else:
            ch.bad = bool(ch.rng.random() < p_gb)
        return bool(ch.rng.random() < (loss_bad if ch.bad else loss_good))

    def offer(self, sender: int, sender_xy: tuple[float, float], receiver_xy: tuple[float, float],
              stamp: float, payload: Any) -> bool:
        """A message arrived from ``sender``; queue it for delivery or drop it. True if queued."""
        c = self.counters
        link = self._link(sender)
        c.received += 1
        link.received += 1
        if math.hypot(sender_xy[0] - receiver_xy[0], sender_xy[1] - receiver_xy[1]) > self.cfg.comm_range:
            c.dropped_range += 1
            link.dropped_range += 1
            return False
        if self.lost(sender):
            c.dropped_loss += 1
            link.dropped_loss += 1
            return False
        delay = self.cfg.latency_ms
        if self.cfg.jitter_ms > 0:
            delay += self._channel(sender).rng.uniform(0.0, self.cfg.jitter_ms)
        heapq.heappush(self._queue, (stamp + delay / 1000.0, sender, next(self._tie), payload))
        return True

    def ready(self, now: float) -> list[Any]:
        """Messages whose latency has elapsed by ``now`` (receiver clock), oldest first."""
        out = []
        while self._queue and self._queue[0][0] <= now + 1e-9:
            _, sender, _, payload = heapq.heappop(self._queue)
            self._link(sender).delivered += 1
            out.append(payload)
        self.counters.delivered += len(out)
        return out

    def _link(self, sender: int) -> RadioCounters:
        link = self.by_sender.get(sender)
        if link is None:
            link = self.by_sender[sender] = RadioCounters()
        return link

    def links(self) -> dict[int, dict[str, int]]:
        """Per sender, what this receiver's model did with its messages so far (cumulative): the value of
        ``Diag.links``, from which a recorder draws the comm graph (delivered / dropped by range / by loss)."""
        return {sender: {"delivered": c.delivered, "dropped_range": c.dropped_range, "dropped_loss": c.dropped_loss}
                for sender, c in sorted(self.by_sender.items())}

    @property
    def pending(self) -> int:
        return len(self._queue)


def config_from_scenario(comm: Any, comm_range: float, seed: int) -> RadioConfig:
    """Build from a :class:`stack.scenario.CommConfig`-shaped object (duck-typed: comm imports nothing of ours)."""
    burst = None
    if comm.burst is not None:
        b = comm.burst
        burst = (b.p_good_bad, b.p_bad_good, b.loss_good, b.loss_bad)
    return RadioConfig(comm_range=comm_range, loss=comm.loss, latency_ms=comm.latency_ms,
                       jitter_ms=comm.jitter_ms, burst=burst, seed=seed)
