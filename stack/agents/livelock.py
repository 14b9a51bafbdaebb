"""No livelock (ours, issue 19): a stuck detector with an escape, and a bound on the leader's hold.

Stuck: a robot not at its target (farther than ``at_target``) whose distance to its slot or goal has
not fallen by ``min_progress`` over the last ``window`` seconds, while it moved (net) less than
``min_travel`` (a follower trailing a moving slot at a constant lag is moving, not stuck). A stuck
robot starts a *stuck episode* and escapes: its target becomes a waypoint toward the side of its
newest scan with more clearance (as far as its body can drive straight there, at most
``escape_distance``: :func:`clear_side_waypoint`),
for at most ``escape_time`` seconds or until it is within ``waypoint_tol`` of it; then it resumes.
The first try is an ``escape`` (short, to the clearer side), later ones ``detour``s (twice as far,
alternating sides). Before each of those, where the robot's memory of its scans (:mod:`.detour`) holds
something between it and its target and a way round it, the try is a ``plan``: the robot follows a grid
path on that memory (re-planned as it sees more; the step drives it with the PID tracker, since the policy's own
steering is what left it stuck) until the straight way to its target is wide open, for at most
``detour.max_time`` seconds; so tries alternate plan, blind, plan. The episode ends, counted by what
resolved it, when the distance falls by ``min_progress`` from where it stood after the last try (``plan``,
``escape`` / ``detour``), when the robot
reaches its target (``target``), or after ``max_tries`` tries without progress (``gave_up``; the
robot goes on under its controller and may be flagged again one window later).

Hold: the leader's connectivity hold (``DecisionLayer.leader_speed``'s ``hold``) slows the leader
while its farthest robot is far. Held (slower than eq. (20) alone) for ``max_hold`` seconds, the
leader gives up on that robot: it goes on at ``resume_fraction`` of the eq. (20) speed, and the
give-up is recorded (when, which robot, how far, why) until the hold lets go again.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..planning.runner import PlanRunner
from ..settings import check, rule
from .detour import DetourConfig, DetourPlanner, ScanMemory

RESOLUTIONS = ("escape", "detour", "target", "gave_up", "plan")
MAX_EVENTS = 20  # give-ups and episodes kept for the diag (the counters count them all)


@dataclass(frozen=True)
class StuckConfig:
    """The stuck detector (defaults: 0.3 m in 8 s). Unknown keys are errors (a dataclass)."""

    enabled: bool = True
    """False: no detection, no escapes (the paper's decision layer alone)."""
    window: float = field(default=8.0, metadata=rule("> 0"))
    """T [s]: the window over which progress is judged."""
    min_progress: float = field(default=0.3, metadata=rule(">= 0"))
    """X [m]: the distance to the target must fall by at least this over the window."""
    min_travel: float = field(default=1.0, metadata=rule(">= 0"))
    """[m] a robot whose net displacement over the window is at least this is moving, not stuck."""
    at_target: float = field(default=1.0, metadata=rule(">= 0"))
    """[m] a robot this near its target is not stuck (and a stuck episode ends with ``target``)."""
    escape_time: float = field(default=4.0, metadata=rule("> 0"))
    """[s] the longest one escape (or detour) drives to its waypoint."""
    escape_distance: float = field(default=1.5, metadata=rule("> 0"))
    """[m] the farthest an escape waypoint lies (a detour: twice this)."""
    waypoint_tol: float = field(default=0.4, metadata=rule("> 0"))
    """[m] a waypoint this near is reached (the try ends early)."""
    max_tries: int = field(default=3, metadata=rule(">= 0"))
    """plans + escapes + detours per stuck episode before giving up."""
    detour: DetourConfig = field(default_factory=DetourConfig)
    """the planned detour on the memory of the robot's scans (:mod:`.detour`)."""

    def __post_init__(self):
        check(self)


@dataclass(frozen=True)
class HoldConfig:
    """The bound on the leader's connectivity hold. Unknown keys are errors (a dataclass)."""

    max_hold: float = 20.0
    """H [s]: the longest the hold may slow the leader before it gives up on the robot it waits for."""
    resume_fraction: float = 0.5
    """after giving up: this fraction of the eq. (20) speed (the hold no longer applies)."""


def free_run(scan: np.ndarray, ang: np.ndarray, range_max: float, heading: np.ndarray, radius: float) -> np.ndarray:
    """How far (m, centre travel) the robot can drive straight along each of ``heading`` (robot frame) before its
    body (``radius`` + 0.1 m) meets a return of ``scan``; ``range_max`` where nothing is in the way. A return
    already nearer than that only blocks a path that would bring the robot 2 cm nearer still (it can leave)."""
    hit = scan < range_max - 1e-6
    px, py = scan[hit] * np.cos(ang[hit]), scan[hit] * np.sin(ang[hit])  # (H,) the returns
    clear = np.minimum(radius + 0.1, np.hypot(px, py) - 0.02)  # (H,)
    ux, uy = np.cos(heading)[:, None], np.sin(heading)[:, None]  # (C, 1)
    along, across = px * ux + py * uy, np.abs(py * ux - px * uy)  # (C, H)
    blocks = (along > 0) & (across < clear)
    stop = np.where(blocks, along - np.sqrt(np.maximum(clear ** 2 - across ** 2, 0.0)), np.inf)
    return np.clip(stop.min(axis=1, initial=np.inf), 0.0, range_max)


def clear_side_waypoint(x: float, y: float, yaw: float, scan: np.ndarray, fov: float, range_max: float,
                        radius: float, reach: float, side: int = 0) -> tuple[tuple[float, float], int]:
    """A waypoint on the side (+1 left, -1 right) of ``scan`` with more clearance (``side`` 0: pick it):
    of the headings 20..100 degrees off the robot's to that side, the one the body can drive farthest along
    (up to ``reach``; the most forward of those that reach it), that far. Beams evenly over -fov/2..fov/2."""
    scan = np.asarray(scan, float).ravel()
    if scan.size == 0:
        scan = np.full(2, range_max)
    ang = np.linspace(-fov / 2, fov / 2, scan.size)
    if side == 0:
        left, right = scan[ang > 0], scan[ang < 0]
        side = 1 if (left.mean() if left.size else 0.0) >= (right.mean() if right.size else 0.0) else -1
    heading = side * np.radians(np.arange(20.0, 101.0, 5.0))
    run = np.minimum(free_run(scan, ang, range_max, heading, radius), reach)
    k = int(np.argmax(run >= run.max() - 1e-9))  # the first (most forward) of the longest
    d, a = max(0.0, float(run[k])), float(heading[k])
    return (x + d * math.cos(yaw + a), y + d * math.sin(yaw + a)), side


class StuckDetector:
    """Per robot: feed :meth:`update` every control step; it says where to go while escaping."""

    def __init__(self, cfg: StuckConfig | None = None, radius: float = 0.5):
        self.cfg = cfg or StuckConfig()
        dc = self.cfg.detour
        self.memory = ScanMemory(dc.resolution, dc.max_cells)
        self.planner = DetourPlanner(dc, self.memory, radius)
        self.plan_until = 0.0
        self.plan_from = (0.0, 0.0)  # where the plan under way began
        self.straight = False  # the plan under way goes down a straight way that was open when it began
        self.samples: deque[tuple[float, float, float, float]] = deque()  # (t, d, x, y)
        self.episodes = 0
        self.resolved = dict.fromkeys(RESOLUTIONS, 0)
        self.events: list[dict] = []
        self.open: dict | None = None  # the stuck episode under way: start, tries, side, kind
        self.waypoint: tuple[float, float] | None = None
        self._target: tuple[float, float] | None = None  # the target a try's plan was asked toward
        self.until = 0.0
        self.runner = PlanRunner()  # inline; the step pipeline hands it the agent's (plans beside the step)
        self._replanned: bool | None = None  # a re-plan under way came back: whether it found a path
        self._first: tuple[bool, tuple[float, float], float] | None = None  # a try's plan came back: found, from, at

    def pause(self) -> None:
        """No judgement this step (no target, or the leader holding on purpose): the window starts again."""
        self.samples.clear()

    def stuck(self) -> bool:
        """Whether the samples span the window without progress or travel."""
        c, s = self.cfg, self.samples
        if s[-1][0] - s[0][0] < c.window - 1e-9:
            return False
        t0, d0, x0, y0 = s[0]
        t1, d1, x1, y1 = s[-1]
        gained = d0 - min(d for _, d, _, _ in s)
        return gained < c.min_progress and math.hypot(x1 - x0, y1 - y0) < c.min_travel

    def _close(self, t: float, how: str) -> None:
        self.resolved[how] += 1
        self._event({"t": round(t, 2), "event": "resolved", "by": how, "tries": self.open["tries"],
                     "stuck_s": round(t - self.open["start"], 2)})
        self.open, self.waypoint = None, None
        self.samples.clear()

    def _event(self, e: dict) -> None:
        self.events = (self.events + [e])[-MAX_EVENTS:]

    def remember(self, x: float, y: float, yaw: float, scan: np.ndarray, fov: float, range_max: float,
                 robots: list[tuple[float, float]] = ()) -> None:
        """Add a scan taken at (x, y, yaw) to the memory the planned detour uses (not the ``robots``' returns)."""
        if self.cfg.enabled and self.cfg.detour.enabled:
            self.memory.add(x, y, yaw, scan, fov, range_max, robots)

    def update(self, t: float, x: float, y: float, yaw: float, d: float, scan: np.ndarray, *, fov: float,
               range_max: float, radius: float, target: tuple[float, float] | None = None) -> tuple[float, float] | None:
        """One control step at (x, y, yaw), ``d`` from ``target``: the waypoint to drive to, or None."""
        c = self.cfg
        if not c.enabled:
            return None
        if self.open is not None and self.open["kind"] == "plan-wait":  # a try's plan is computing beside the step
            if self._first is None:
                return None  # the policy drives on meanwhile (the guard under it)
            return self._planned_try(t, x, y, yaw, scan, fov, range_max, radius)
        if self.waypoint is not None:  # escaping
            if self.open is not None and self.open["kind"] == "plan":
                wp = self._follow(t, (x, y), target)
                if wp is not None:
                    self.waypoint = wp
                    return wp
            elif t < self.until and math.hypot(x - self.waypoint[0], y - self.waypoint[1]) > c.waypoint_tol:
                return self.waypoint
            self.waypoint = None
            self.samples.clear()  # the progress window starts where the try left the robot
        if self.open is not None and d <= c.at_target:
            self._close(t, "target")
        self.samples.append((t, d, x, y))
        while len(self.samples) > 1 and self.samples[-1][0] - self.samples[1][0] >= c.window:
            self.samples.popleft()
        if d <= c.at_target:
            self.samples.clear()
            return None
        if self.open is not None and self.samples[0][1] - d >= c.min_progress:
            self._close(t, self.open["kind"])
            return None
        if not self.stuck():
            return None
        return self._try(t, x, y, yaw, scan, fov, range_max, radius, target)

    def _follow(self, t: float, me: tuple[float, float], target) -> tuple[float, float] | None:
        """A planned detour under way: the next waypoint on the path (re-planned every ``replan_s``, beside the step:
        the last path is followed meanwhile), or None when it is over (time is up, no path any more, or the straight
        way to the target is open; a plan down a way that was open from the start ends once the robot is
        ``open_horizon`` along it)."""
        dc = self.cfg.detour
        if t >= self.plan_until or target is None:
            return None
        if t - self.planner.planned_at >= dc.replan_s and not self.runner.busy("detour"):
            self.runner.submit("detour", self.planner.ask(t, me, target).run, self._on_replan)
        if self._replanned is not None:
            found, self._replanned = self._replanned, None
            if not found:
                return None
            along = math.hypot(me[0] - self.plan_from[0], me[1] - self.plan_from[1])
            if self.planner.open_line(me, target) and not (self.straight and along < dc.open_horizon):
                return None
        return self.planner.waypoint(me)

    def _on_replan(self, found) -> None:
        if self.open is not None and self.open["kind"] == "plan":  # the detour is still under way
            self._replanned = self.planner.adopt(found)

    def _plan(self, t: float, me: tuple[float, float], target) -> bool:
        """Ask for a planned detour (inline it is back at once: ``self._first``). Where the straight way to the
        target is open in the memory the robot is stuck all the same (its policy's own steering refuses the way:
        Deng's obstacle term repels every direction through a gap), so the tracker drives down the way for
        ``open_horizon`` metres, ``straight_time`` at most. False: no plan asked (disabled, no target, or the last
        detour's re-plan still computing)."""
        dc = self.cfg.detour
        if not dc.enabled or target is None or self.runner.busy("detour"):  # busy: the last detour's re-plan
            return False
        self._first = None
        self.runner.submit("detour", self.planner.ask(t, me, target).run,
                           lambda found: self._on_first(found, me, t))
        return True

    def _on_first(self, found, me: tuple[float, float], t: float) -> None:
        if self.open is not None and self.open["kind"] == "plan-wait":
            self._first = (self.planner.adopt(found), me, t)

    def _planned_try(self, t, x, y, yaw, scan, fov, range_max, radius) -> tuple[float, float] | None:
        """A try's plan is back: follow it, or (no way round) the next blind try."""
        (found, me, t_asked), self._first = self._first, None
        o, dc = self.open, self.cfg.detour
        self._replanned = None  # a re-plan of an earlier detour that came back after it ended
        if not found:
            o["kind"] = "escape" if o["blind"] == 0 else "detour"
            return self._blind(t, x, y, yaw, scan, fov, range_max, radius)
        self.straight = self.planner.open_line(me, self._target)
        self.plan_from = me
        self.plan_until = t_asked + (min(dc.straight_time, dc.max_time) if self.straight else dc.max_time)
        self.waypoint, o["kind"] = self.planner.waypoint((x, y)), "plan"
        return self.waypoint

    def _try(self, t, x, y, yaw, scan, fov, range_max, radius, target=None) -> tuple[float, float] | None:
        """Stuck: open an episode if none is open, then the next try: a plan where one helps (first, then every
        other try), else the next escape / detour (or give up)."""
        c = self.cfg
        if self.open is None:
            self.episodes += 1
            self.open = {"start": t, "tries": 0, "side": 0, "kind": "escape", "blind": 0}
            self._event({"t": round(t, 2), "event": "stuck", "d": round(self.samples[-1][1], 2)})
        o = self.open
        if o["tries"] >= c.max_tries:
            self._close(t, "gave_up")
            return None
        o["tries"] += 1
        if o["kind"] != "plan":
            kind, o["kind"], self._target = o["kind"], "plan-wait", target
            if self._plan(t, (x, y), target):
                return None if self._first is None else self._planned_try(t, x, y, yaw, scan, fov, range_max, radius)
            o["kind"] = kind
        return self._blind(t, x, y, yaw, scan, fov, range_max, radius)

    def _blind(self, t, x, y, yaw, scan, fov, range_max, radius) -> tuple[float, float]:
        """The next escape (the first blind try) or detour (later ones, the other side from the last)."""
        c, o = self.cfg, self.open
        kind = "escape" if o["blind"] == 0 else "detour"
        reach = c.escape_distance * (1 if kind == "escape" else 2)
        side = 0 if o["blind"] == 0 else -o["side"]  # a detour tries the other side from the last try
        self.waypoint, o["side"] = clear_side_waypoint(x, y, yaw, scan, fov, range_max, radius, reach, side)
        o["blind"] += 1
        o["kind"] = kind
        self.until = t + c.escape_time
        return self.waypoint

    @property
    def escaping(self) -> bool:
        return self.waypoint is not None

    @property
    def planned(self) -> bool:
        """Whether the robot is following a planned detour (the step drives it with the path tracker: a policy's own
        steering is what left it stuck)."""
        return self.waypoint is not None and self.open is not None and self.open["kind"] == "plan"


class HoldGuard:
    """The leader's hold with a bound: :meth:`speed` every control step (see the module docstring)."""

    def __init__(self, cfg: HoldConfig | None = None):
        self.cfg = cfg or HoldConfig()
        self.since: float | None = None  # when the current hold began
        self.given_up: dict | None = None  # the give-up in force
        self.give_ups = 0
        self.events: list[dict] = []
        self.used = False  # whether the agent drives the leader through :meth:`speed` at all

    @property
    def holding(self) -> bool:
        """Whether the hold is slowing the leader on purpose (and has not given up)."""
        return self.since is not None and self.given_up is None

    def speed(self, v20: float, factor: float, t: float, waiting_for: tuple[int, float] | None) -> float:
        """The command at time ``t`` from the eq. (20) speed ``v20`` and the hold's ``factor`` (1: no hold);
        ``waiting_for``: (id, distance) of the farthest robot, the one the hold waits for."""
        self.used = True
        if factor >= 1.0:
            if self.given_up is not None:
                self._event({"t": round(t, 2), "event": "hold-released", "robot": self.given_up["robot"]})
            self.since, self.given_up = None, None
            return v20
        if self.since is None:
            self.since = t
        if self.given_up is None and t - self.since >= self.cfg.max_hold:
            rid, d = waiting_for if waiting_for is not None else (None, math.nan)
            held = t - self.since
            self.given_up = {"t": round(t, 2), "event": "hold-gave-up", "robot": rid, "d_rmax": round(d, 2),
                             "held_s": round(held, 2),
                             "reason": f"held {held:.1f} s >= max_hold {self.cfg.max_hold:g} s waiting for robot {rid} "
                                       f"at {d:.1f} m; resuming at {self.cfg.resume_fraction:g} x eq. (20)"}
            self.give_ups += 1
            self._event(self.given_up)
        if self.given_up is not None:
            return v20 * max(factor, self.cfg.resume_fraction)
        return v20 * factor

    def _event(self, e: dict) -> None:
        self.events = (self.events + [e])[-MAX_EVENTS:]
