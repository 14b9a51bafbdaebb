"""The decision layer of Bai 2022 section IV (Algorithm 2): which target, which controller.

Leader (section IV-A):
  situation 1: min(d_rmin, d_omin) > d_safe  or  d_g < min(d_rmin, d_omin)  -> PID to the goal
  situation 2: otherwise                                                   -> the network to the goal
  eq. (20):    v_L <- v_L * 5 / d_rmax  when d_rmax > 5 m
Follower (section IV-B), target from eq. (3):
  situation 1: min(d_rmin, d_omin) > d_safe                 -> PID to the slot
  situation 2: d_rmin < d_safe and d_omin > d_safe          -> the network to the slot
  situation 3: otherwise (an obstacle within d_safe)        -> the network, d_g to the slot but
               alpha_g toward the centre (eq. 22) of the robots selected by eq. (21)

d_rmin/d_rmax come from the neighbours' reported states (as delivered by the radio
model); d_omin from the lidar, leaving out beams that end on a known neighbour.

No livelock (ours, :mod:`.livelock`): a robot whose distance to its target has not fallen for a
window is stuck and drives, for a bounded time, along a path planned on the memory of its scans
(:mod:`.detour`) or to a blind escape / detour waypoint (situation ``escape``); :meth:`DecisionLayer.hold_speed` is eq. (20) with the connectivity hold bounded in time.
:meth:`DecisionLayer.livelock` sums both up for the agent's diag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..models.geometry import polar, slot_position
from ..models.observation import PREDICT_HORIZON_S, neighbour_view, observation_fields, predicted
from ..policies.base import Observation
from .livelock import RESOLUTIONS, HoldConfig, HoldGuard, StuckConfig, StuckDetector

DEFAULT_HOLD_START = 0.8  # DrlConfig.leader_hold's default start [fraction of d_com]
SITUATIONS = ("leader-1", "leader-2", "follower-1", "follower-2", "follower-3", "peer", "waiting", "escape")


@dataclass
class Neighbour:
    id: int
    role: str
    x: float
    y: float
    yaw: float
    v: float
    w: float
    stamp: float  # sender's stamp
    seq: int
    d_goal: float | None = None  # arrival-time peers: its distance to its own goal, as it reported

    def predicted(self, now: float, horizon: float = PREDICT_HORIZON_S) -> tuple[float, float]:
        """Position extrapolated along the reported velocity, at most ``horizon`` seconds."""
        return predicted(self.x, self.y, self.yaw, self.v, now - self.stamp, horizon)

    def report(self, now: float) -> tuple:
        """(x, y, yaw, v, w, age, d_goal): what :func:`stack.models.observation.neighbour_view` reads."""
        return self.x, self.y, self.yaw, self.v, self.w, now - self.stamp, self.d_goal


@dataclass
class Decision:
    situation: str
    use_network: bool
    obs: Observation | None  # None: hold still (e.g. a follower that has not heard its leader yet)
    target: tuple[float, float] | None
    d_rmin: float
    d_rmax: float
    d_omin: float


def obstacle_distance(pose_xy: tuple[float, float], yaw: float, scan: np.ndarray, angle_min: float, angle_inc: float,
                      range_max: float, neighbours: list[tuple[float, float]], robot_radius: float) -> float:
    """Smallest lidar range whose end point is not on a known neighbour (within its radius + 0.3 m)."""
    if scan.size == 0:
        return math.inf
    hits = scan < range_max - 1e-6
    if not hits.any():
        return math.inf
    r = scan[hits]
    ang = yaw + angle_min + angle_inc * np.nonzero(hits)[0]
    ex, ey = pose_xy[0] + r * np.cos(ang), pose_xy[1] + r * np.sin(ang)
    keep = np.ones(r.shape, bool)
    for nx, ny in neighbours:
        keep &= np.hypot(ex - nx, ey - ny) > robot_radius + 0.3
    return float(r[keep].min()) if keep.any() else math.inf


class DecisionLayer:
    def __init__(self, robot_id: int, role: str, formation, *, goal: tuple[float, float] | None, radius: float,
                 comm_range: float, scan_range: float, dt: float, centre_heading: bool = True,
                 stuck: StuckConfig | None = None, hold: HoldConfig | None = None, fov: float = math.pi):
        """``centre_heading``: in follower situation 3, aim at the centre of the selected robots (eq. 21-22).
        Meant for a network that avoids obstacles; a policy without avoidance (``pid``) keeps aiming at its slot.
        ``stuck``, ``hold``: the stuck detector and the hold's bound (:mod:`.livelock`, defaults there);
        ``fov``: the lidar's field of view (beams evenly over -fov/2..fov/2) for the escape's clear side."""
        self.id = robot_id
        self.role = role
        self.formation = formation
        self.goal = goal
        self.radius = radius
        self.comm_range = comm_range
        self.scan_range = scan_range
        self.dt = dt
        self.centre_heading = centre_heading
        self.counts: dict[str, int] = {s: 0 for s in SITUATIONS}
        self.fov = fov
        self.stuck = StuckDetector(stuck, radius)
        self.hold = HoldGuard(hold)
        self.farthest: tuple[int, float] | None = None  # (id, distance) of the farthest neighbour (the hold's)
        self.target: tuple[float, float] | None = None  # the last decision's formation target, before any escape
        self.static_hold = True  # False: no hold slows this leader at all (a policy that drives itself: aina, qlearn)

    def decide(self, pose, now: float, neighbours: dict[int, Neighbour], scans: np.ndarray, d_omin: float,
               t_run: float | None = None, dead: set[int] | frozenset[int] = frozenset()) -> Decision:
        """``now``: the clock of the neighbours' stamps; ``t_run``: time since the run began (the
        formation schedule's clock; defaults to ``now``); ``dead``: robots known to be gone (the
        formation's failover rule may make this robot the leader: ``self.role`` follows it).
        A stuck robot's decision is ``escape``: the network (or a policy that drives alone) to a waypoint."""
        t_run = now if t_run is None else t_run
        view = neighbour_view((pose.x, pose.y), pose.yaw, [n.report(now) for n in neighbours.values()], self.comm_range)
        self.farthest = max(zip(neighbours, view.dists), key=lambda p: p[1], default=None)

        def obs(target, alpha=None, gvel=(0.0, 0.0), target_yaw=None) -> Observation:
            return Observation(**observation_fields(pose.x, pose.y, pose.yaw, pose.v, pose.w, target, view, scans=scans,
                                                    scan_range=self.scan_range, dt=self.dt, goal_velocity=gvel,
                                                    target_yaw=target_yaw, alpha=alpha))

        dec = self._situation(pose, now, neighbours, view, obs, d_omin, t_run, dead)
        self.target = dec.target  # leader, peer: the goal; follower: its slot (eq. 3); None while waiting
        if dec.target is None or (self.role == "leader" and self._held(dec.d_rmax)):
            self.stuck.pause()  # nothing to go to, or held on purpose (bounded by the hold's own clock)
            return self._count(dec)
        sc = np.asarray(scans, float)
        newest = sc[-1] if sc.ndim == 2 and len(sc) else sc.ravel()
        self.stuck.remember(pose.x, pose.y, pose.yaw, newest, self.fov, self.scan_range,
                            [n.predicted(now) for n in neighbours.values()])
        wp = self.stuck.update(t_run, pose.x, pose.y, pose.yaw, dec.obs.d_g, newest, fov=self.fov,
                               range_max=self.scan_range, radius=self.radius, target=dec.target)
        if wp is not None:
            dec = Decision("escape", True, obs(wp), wp, dec.d_rmin, dec.d_rmax, dec.d_omin)
        return self._count(dec)

    def set_goal(self, goal: tuple[float, float]) -> None:
        """A new goal in the site frame: the formation's (used while this robot leads) or, for an arrival-time
        peer, its own; followers' slots stay relative to the leader. The stuck detector's window starts again."""
        if self.formation is None:
            self.goal = goal
        else:
            self.formation = replace(self.formation, goal=goal)
        self.stuck.pause()

    def _held(self, d_rmax: float) -> bool:
        """Whether the leader's hold slows it on purpose (last step). An agent that never calls :meth:`hold_speed`
        (the static :meth:`leader_speed` alone) holds from the default hold's start (0.8 d_com) on, unless
        ``static_hold`` is off (a policy that drives itself, which no hold slows)."""
        if self.hold.used:
            return self.hold.holding
        return self.static_hold and d_rmax >= DEFAULT_HOLD_START * self.comm_range

    def _situation(self, pose, now, neighbours, view, obs, d_omin, t_run, dead) -> Decision:
        """Section IV's situations (Algorithm 2)."""
        me = (pose.x, pose.y)
        others, d_rmin, d_rmax = view.others, view.d_rmin, view.d_rmax

        f = self.formation
        if f is None:  # arrival-time peer: straight to its own goal
            return Decision("peer", False, obs(self.goal), self.goal, d_rmin, d_rmax, d_omin)
        d_safe = f.d_safe
        leader_id, slots = f.resolve(t_run, dead)
        self.role = "leader" if leader_id == self.id else "follower"
        if self.role == "leader":
            d_g = polar(me, pose.yaw, f.goal)[0]
            m = min(d_rmin, d_omin)
            if m > d_safe or d_g < m:
                return Decision("leader-1", False, obs(f.goal), f.goal, d_rmin, d_rmax, d_omin)
            return Decision("leader-2", True, obs(f.goal), f.goal, d_rmin, d_rmax, d_omin)

        leader = neighbours.get(leader_id)
        if leader is None or self.id not in slots:
            return Decision("waiting", False, None, None, d_rmin, d_rmax, d_omin)
        lx, ly = leader.predicted(now)
        slot = slots[self.id]  # formation.schedule switches the slots in time; failover re-assigns them
        target = slot_position((lx, ly), slot)  # eq. (3)
        gvel = (leader.v * math.cos(leader.yaw), leader.v * math.sin(leader.yaw))
        if min(d_rmin, d_omin) > d_safe:
            return Decision("follower-1", False, obs(target, gvel=gvel, target_yaw=leader.yaw), target,
                                        d_rmin, d_rmax, d_omin)
        if d_rmin < d_safe and d_omin > d_safe:
            return Decision("follower-2", True, obs(target, gvel=gvel, target_yaw=leader.yaw), target,
                                        d_rmin, d_rmax, d_omin)
        # situation 3: eq. (21) selects robots i with cos<p_L - p_F, p_i - p_F> > 0, eq. (22) their centre
        lv = (lx - me[0], ly - me[1])
        sel = [o for o in others if lv[0] * (o[0] - me[0]) + lv[1] * (o[1] - me[1]) > 0]
        if sel and self.centre_heading:
            xc, yc = sum(o[0] for o in sel) / len(sel), sum(o[1] for o in sel) / len(sel)
            alpha = polar(me, pose.yaw, (xc, yc))[1]
        else:
            alpha = None
        return Decision("follower-3", True, obs(target, alpha=alpha, gvel=gvel, target_yaw=leader.yaw), target,
                                    d_rmin, d_rmax, d_omin)

    def _count(self, d: Decision) -> Decision:
        self.counts[d.situation] += 1
        return d

    @staticmethod
    def hold_factor(d_rmax: float, hold: tuple[float, float] | None, d_com: float = 10.0) -> float:
        """The connectivity hold's factor on the leader's speed: 1 up to start d_com, falling linearly to 0 at
        stop d_com (ours, beyond eq. 20; 1 without ``hold``)."""
        if hold is None or not math.isfinite(d_rmax):
            return 1.0
        start, stop = hold[0] * d_com, hold[1] * d_com
        return min(1.0, max(0.0, (stop - d_rmax) / (stop - start)))

    @staticmethod
    def leader_speed(v: float, d_rmax: float, d_slow: float = 5.0, hold: tuple[float, float] | None = None,
                     d_com: float = 10.0) -> float:
        """Eq. (20): v_L^c (5 / d_L^rmax) if d_L^rmax > 5 m.

        ``hold`` (ours, beyond eq. 20): (start, stop) as fractions of ``d_com``. Eq. (20) still leaves the leader
        at half speed when a follower is 10 m away, so a follower held up at an obstacle falls out of range;
        with ``hold`` the speed also falls linearly to zero as d_rmax goes from start d_com to stop d_com.
        Unbounded in time: :meth:`hold_speed` is the same with the hold's bound."""
        if d_rmax > d_slow:
            v = v * (d_slow / d_rmax)
        return v * DecisionLayer.hold_factor(d_rmax, hold, d_com)

    def hold_speed(self, v: float, d_rmax: float, t_run: float, d_slow: float = 5.0,
                   hold: tuple[float, float] | None = None, d_com: float = 10.0) -> float:
        """:meth:`leader_speed` at time ``t_run`` with the hold bounded: held for ``HoldConfig.max_hold`` seconds,
        the leader gives up on its farthest robot (recorded in :attr:`hold`), going on at a reduced speed."""
        v20 = self.leader_speed(v, d_rmax, d_slow, None, d_com)
        return self.hold.speed(v20, self.hold_factor(d_rmax, hold, d_com), t_run, self.farthest)

    def livelock(self) -> dict:
        """The livelock counters for the diag (``Diag.stuck``): stuck episodes, what resolved them, whether one
        is open, the hold's give-ups, and the latest events (stuck / resolved / hold-gave-up / hold-released)."""
        st, h = self.stuck, self.hold
        events = sorted(st.events + h.events, key=lambda e: e["t"])[-20:]
        return {"episodes": st.episodes, **{k: st.resolved[k] for k in RESOLUTIONS}, "open": int(st.open is not None),
                "hold_give_ups": h.give_ups, "events": events}
