"""The lock-step barrier, both sides of it: the world's wait for every live agent's step-k command, and the
agent's wait for step k's inputs.

A lock-step run is the special case in which the world's clock drives everything: per step k the world
publishes ``world/clock`` (k, t, who answered k-1, who is dead, how many odometry samples each hosted device
has sent), the sensors of step k, then waits (``CommandBarrier``) until every live agent has commanded step k
and (``DeviceWires``) until each hosted device has those commands.
An agent (``StepBarrier``) waits until step k's inputs are all in, then for the states that the robots which
answered k-1 sent before their command, so that every agent computes step k from the same messages, whatever
the wall clock does.

Device odometry carries no step (CAN encoder frames, MAVLink telemetry, a bridged base's ``Odometry``): the
clock's ``device_odom`` counts the samples each device has sent since lock-step began. The world sends step
k's samples only after every agent has commanded k-1, so the samples an agent receives between its commands
of k-1 and k are exactly step k's; the agent waits for ``device_odom[k] - device_odom[k-1]`` of them (bounded
by ``device_wait_s``: a sample lost on the wire is counted in ``device_late``, never a stall). Samples beyond
that count (sent before lock-step began, or left in a device's buffer by a killed agent) precede the step's
own on the same wire: the newest ``n`` are the step's, the older ones are dropped and counted as ``strays``.
An agent's first step (a fresh start or a restart) is a sync step: it takes no device sample (it drops all
before it, uncounted: how many there are says how long the device ran on the wall clock) and so commands zero;
the world sends no device telemetry before step 1. What remains is a sample sent before lock-step began that is
still on its wire after the agent's whole first step: it would count for step 1 (and the next step's count
then drops it).

The other way, a device agent's command of step k goes over the device's wire and its answer over zenoh, in no
order between them: the answer counts the messages its driver has put on that wire, and the world takes the
device's commands until the device has handled as many (``DeviceWires``).

Wall time enters only as the bounds of these waits (a stalled or lost peer); a run in which no bound
expires is the same run every time.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Iterable, Mapping

import msgspec

from .messages import Clock, Relayed

log = logging.getLogger("stack.lockstep")


class CommandBarrier:
    """World side: step k's commands, per robot, and the wait for every live, responsive agent's.

    ``cv`` is the world's condition (its callbacks hold it while they update ``live``); ``live()`` returns the
    robots whose liveliness token is up. An agent that does not answer within ``timeout_s`` (wall) is marked
    unresponsive and not waited for until it answers again.
    """

    def __init__(self, cv: threading.Condition, live: Callable[[], set[int]], timeout_s: float):
        self._cv = cv
        self._live = live
        self.timeout_s = timeout_s
        self.cmds: dict[int, dict[int, tuple[float, float] | None]] = {}  # step -> id -> (v, w) (None: on a device's wire)
        self.wires: dict[int, dict[int, tuple[int, bool]]] = {}  # step -> id -> (messages on its device's wire, sync)
        self.unresponsive: set[int] = set()
        self.step = 0  # the step being waited for

    def answered(self, rid: int, step: int, cmd: tuple[float, float] | None,
                 wire: tuple[int, bool] | None = None) -> None:
        """Robot ``rid`` has commanded ``step`` (caller holds the condition); ``wire``: a device's driver's
        (``Answer.wire``, ``Answer.sync``), for ``DeviceWires``."""
        if step < 0:
            return
        got = self.cmds.setdefault(step, {})
        got[rid] = cmd
        if wire is not None:
            self.wires.setdefault(step, {})[rid] = wire
        self.unresponsive.discard(rid)
        if step == self.step and len(got) >= len(self._live() - self.unresponsive):
            self._cv.notify_all()  # wake the world once the step may be complete

    def responsive(self, ids: Iterable[int]) -> None:
        """Wait for these again (e.g. restarted agents; caller holds the condition)."""
        self.unresponsive -= set(ids)

    def wait(self, k: int, stop: threading.Event) -> list[int]:
        """Until every live, responsive agent has commanded step ``k``; returns the ones given up on."""
        deadline = time.monotonic() + self.timeout_s
        with self._cv:
            self.step = k
            while True:
                waiting = (self._live() - self.unresponsive) - set(self.cmds.get(k, {}))
                if not waiting or stop.is_set():
                    return []
                if time.monotonic() > deadline:
                    log.warning("world: step %d: no command from %s within %.1f s: not waiting for them", k,
                                sorted(waiting), self.timeout_s)
                    self.unresponsive |= waiting
                    return sorted(waiting)
                self._cv.wait(0.1)

    def take(self, k: int) -> dict[int, tuple[float, float] | None]:
        """Step ``k``'s commands (caller holds the condition); older steps' are forgotten."""
        got = self.cmds.pop(k, {})
        for old in [s for s in self.cmds if s < k]:
            del self.cmds[old]
        return got

    def take_wires(self, k: int) -> dict[int, tuple[int, bool]]:
        """Step ``k``'s device wire counts (caller holds the condition); older steps' are forgotten."""
        got = self.wires.pop(k, {})
        for old in [s for s in self.wires if s < k]:
            del self.wires[old]
        return got


class DeviceWires:
    """World side, the hosted devices' half of step k's commands: each device handles every message its driver
    had put on its wire when the agent answered k, before the world moves the body.

    The answer and the command travel on different wires (zenoh for the answer; a pty, a UDP socket or another
    zenoh key for the command), and no order holds between them: each zenoh subscriber runs its callbacks on its
    own thread (zenoh-python's default), so a bridged Jackal's ``cmd_vel`` can reach the device after the answer
    reached the world (seen: taken a step late). So the answer says how many messages the driver has put on the wire (``Driver.wire_sent``) and the world
    takes the device's commands (``take_commands``, at the step's time: handling them in one go or in parts is
    the same) until the device has handled that many (``wire_received``). A driver sends messages after its
    answer too (keep-alives on the wall clock): they repeat its last command, so the step they land in changes
    nothing the device does.

    Counts run from the device's start: the first driver to answer is the only one that wrote to it. An agent
    that starts again answers its first step with ``sync`` and a new driver's count: the count is rebased on what
    the device has handled by then (the new driver's opening messages came long before; the first command of a
    sync step is zero).
    """

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self._base: dict[int, int] = {}  # robot -> the device's count when its driver's count began
        self.late = 0  # device-steps that went on without every message of the answer

    def deliver(self, devices: Mapping[int, Any], wires: Mapping[int, tuple[int, bool]], t: float,
                stop: threading.Event) -> list[int]:
        """Every device takes its commands at ``t`` until it has the messages its driver's answer of the step
        counts (bounded by ``timeout_s`` wall: a message lost on its wire is a late step, never a stall);
        returns the robots whose wire fell short."""
        need = {}
        for rid, dev in devices.items():
            dev.take_commands(t)
            if rid in wires:
                need[rid] = self._needed(rid, dev, *wires[rid])
        deadline = time.monotonic() + self.timeout_s
        short = [rid for rid, n in need.items() if devices[rid].wire_received < n]
        while short and not stop.is_set() and time.monotonic() < deadline:
            time.sleep(0.0002)
            for rid in short:
                devices[rid].take_commands(t)
            short = [rid for rid in short if devices[rid].wire_received < need[rid]]
        if short:
            self.late += len(short)
            log.warning("world: t=%.2f s: robots %s: not every message of their answer reached the device within "
                        "%.1f s; going on", t, short, self.timeout_s)
        return short

    def _needed(self, rid: int, dev: Any, wire: int, sync: bool) -> int:
        if sync and rid in self._base:  # a new driver (the agent started again): its count starts here
            self._base[rid] = max(0, dev.wire_received - wire)
        base = self._base.setdefault(rid, 0)
        return base + wire


class _StateHead(msgspec.Struct):
    """The two fields of a ``State`` the relay reads (msgspec skips the rest unparsed)."""

    id: int
    step: int = -1


_HEAD = msgspec.msgpack.Decoder(_StateHead)


class StateRelay:
    """World side, lock-step: the agents' states, heard once on ``*/state`` and handed on undecoded in the next
    clock, so that no agent subscribes per sender (one delivery a step instead of one per neighbour).

    ``take(k-1, answered)`` waits (bounded, ``wait_s`` wall) until the state of step k-1 of every robot that
    commanded k-1 is in (an agent sends its state before its command, on another key, so the world may hear the
    command first) and returns everything heard since the last clock, in arrival order: the agent sorts what it
    takes by (step, id, seq), so the order on the wire decides nothing. The relay reads only each payload's
    ``id`` and ``step``; a payload it cannot read is relayed all the same (it never counts as the awaited state),
    for the agents to decode, validate and count by its key as before.
    """

    def __init__(self, cv: threading.Condition, wait_s: float = 1.0, limit_bytes: int = 4 << 20):
        self._cv = cv
        self.wait_s = wait_s
        self.limit_bytes = limit_bytes  # payload bytes one clock carries at most (beyond: a flood; dropped, counted)
        self.dropped = 0  # payloads dropped over the limit (world.json ``states_dropped``)
        self._heard: list[Relayed] = []
        self._bytes = 0
        self._newest: dict[int, int] = {}  # sender -> the newest step of its states heard
        self._missing: set[int] = set()  # whom take() waits for, of step _step
        self._step = -1
        self.late = 0  # clocks that went out without a state they waited for

    def on_state(self, key: str, payload: bytes) -> None:
        """A payload heard on a state key (any thread; takes the condition)."""
        try:
            head = _HEAD.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError, TypeError, RecursionError):
            head = None
        with self._cv:
            if self._bytes + len(payload) <= self.limit_bytes:
                self._heard.append(Relayed(key=key, payload=payload))
                self._bytes += len(payload)
            else:
                self.dropped += 1
                if self.dropped == 1:
                    log.warning("world: more than %d bytes of states on %s before one clock: dropped (counted in "
                                "world.json states_dropped)", self.limit_bytes, key)
            if head is None:
                return
            self._newest[head.id] = max(head.step, self._newest.get(head.id, -2))
            if head.id in self._missing and head.step >= self._step:
                self._missing.discard(head.id)
                if not self._missing:
                    self._cv.notify_all()  # one wake-up: the last awaited state is in

    def take(self, step: int, answered: Iterable[int], stop: threading.Event) -> list[Relayed]:
        """Every state heard so far, once the state of ``step`` of each robot in ``answered`` is among them (or
        ``wait_s`` has passed: counted in ``late``, logged)."""
        deadline = time.monotonic() + self.wait_s
        with self._cv:
            self._step = step
            self._missing = {i for i in answered if self._newest.get(i, -2) < step}
            while self._missing and not stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    self.late += 1
                    log.warning("world: no state of step %d from %s within %.1f s: the clock goes without", step,
                                sorted(self._missing), self.wait_s)
                    break
                self._cv.wait(min(left, 0.1))
            self._missing = set()
            heard, self._heard, self._bytes = self._heard, [], 0
        return heard


class StepBarrier:
    """Agent side: which step comes next and when its inputs are complete.

    The agent's zenoh callbacks feed it under ``cv`` (``on_clock``, ``on_state``, ``on_sample``); the loop
    calls ``wait_step`` and then ``wait_neighbours``.
    """

    def __init__(self, robot_id: int, cv: threading.Condition, *, neighbour_wait_s: float = 1.0,
                 device_wait_s: float = 2.0, sensor_timeout_s: float = 30.0):
        self.id = robot_id
        self._cv = cv
        self.neighbour_wait_s = neighbour_wait_s
        self.device_wait_s = device_wait_s
        self.sensor_timeout_s = sensor_timeout_s
        self.clocks: dict[int, Clock] = {}  # the newest clocks by step
        self._seen: dict[int, int] = {}  # sender -> newest step of its state seen on the wire
        self._awaited: set[int] = set()
        self._awaited_step = -1
        self._sent_before: int | None = None  # device_odom of our previous step
        self.device_late = 0  # steps that went on without all of the device's samples
        self.strays = 0  # device samples that belonged to no step (dropped)
        self.neighbour_timeouts = 0  # steps that went on without an awaited neighbour state

    # --- fed by the callbacks (caller holds cv) ---------------------------------------------------
    def on_clock(self, m: Clock) -> None:
        self.clocks[m.step] = m
        for old in [s for s in self.clocks if s < m.step - 5]:
            del self.clocks[old]
        self._cv.notify_all()

    def on_state(self, sender: int, step: int) -> None:
        self._seen[sender] = max(self._seen.get(sender, -1), step)
        if self._awaited and sender in self._awaited and step >= self._awaited_step:
            self._awaited.discard(sender)
            if not self._awaited:  # wake the loop once, when the last awaited state is in
                self._cv.notify_all()

    # --- the agent's waits ------------------------------------------------------------------------
    def wait_step(self, last: int, ready: Callable[[int], bool], pending: Callable[[], int],
                  stop: threading.Event, missing: Callable[[int], str] | None = None) -> tuple[Clock, int | None] | None:
        """Block (caller holds cv) until the newest step k > ``last`` has its clock and ``ready(k)`` (the
        scan, a step-carrying driver's sample, the gyro, a due fix), and ``pending()`` device samples number
        step k's count. Returns (clock k, how many of the newest pending samples are step k's; None: the robot
        has no hosted device), or None on ``stop``. No clock or sensors for ``sensor_timeout_s`` is a TimeoutError
        (``missing(k)`` says what step k lacked)."""
        deadline = time.monotonic() + self.sensor_timeout_s
        device_deadline: float | None = None
        while not stop.is_set():
            k = max(self.clocks, default=-1)
            if k > last and ready(k):
                clock = self.clocks[k]
                need = self._device_count(clock)
                if need is None or pending() >= need:
                    break
                device_deadline = device_deadline or time.monotonic() + self.device_wait_s
                if time.monotonic() > device_deadline:
                    self.device_late += 1
                    log.warning("agent %d: step %d: %d of %d device odometry samples within %.1f s; going on",
                                self.id, k, pending(), need, self.device_wait_s)
                    break
            elif time.monotonic() > deadline:
                what = (f" (step {k}: {missing(k)})" if k > last else f" (no clock after step {last})") if missing else ""
                raise TimeoutError(f"agent {self.id}: no sensor data from the world for {self.sensor_timeout_s:.0f} s{what}")
            self._cv.wait(0.05)
        else:
            return None
        need = self._device_count(clock)
        if need is not None and pending() > need and self._sent_before is not None:
            self.strays += pending() - need  # (a sync step's are the device's history: how long it ran before us)
        self._sent_before = clock.device_odom.get(self.id)
        return clock, need

    def _device_count(self, clock: Clock) -> int | None:
        """How many device samples step ``clock.step`` brings (None: the robot has no hosted device). Our first
        step is a sync step: the device's history is unknown, so none of what came before is the step's (the
        agent drops it all and, without odometry, commands zero); from the next step on the counts hold."""
        sent = clock.device_odom.get(self.id)
        if sent is None:
            return None
        if self._sent_before is None:
            return 0
        return max(0, sent - self._sent_before)

    def wait_neighbours(self, clock: Clock, first: bool, stop: threading.Event) -> bool:
        """Block (caller holds cv), bounded, until every robot that answered step k-1 (alive, not us) has had
        its state of k-1 seen. A (re)started agent has nobody to wait for. False on ``stop``."""
        k = clock.step
        if first:
            return True
        self._awaited_step = k - 1
        self._awaited = {i for i in clock.answered if i != self.id and i not in clock.dead
                         and self._seen.get(i, -1) < k - 1}
        t_end = time.monotonic() + self.neighbour_wait_s
        while self._awaited and time.monotonic() < t_end:
            if stop.is_set():
                return False
            self._cv.wait(0.05)
        if self._awaited:  # a sender answered the world but its state never reached us: go on, say so
            self.neighbour_timeouts += 1
            log.warning("agent %d: step %d: no state of step %d from %s within %.1f s; going on without",
                        self.id, k, k - 1, sorted(self._awaited), self.neighbour_wait_s)
        self._awaited = set()
        return True


__all__ = ["CommandBarrier", "DeviceWires", "StateRelay", "StepBarrier"]
