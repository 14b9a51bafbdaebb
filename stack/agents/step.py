"""The control step as a function of its inputs: estimator -> radio model -> decision layer -> policy.

``StepPipeline.step(StepInputs) -> StepOutput`` holds no Zenoh, no driver and no barrier: the agent process
(``agent.py``) gathers the inputs (lock-step: the world's step k, through ``stack.comm.lockstep``; real time:
what arrived by the agent's own tick) and sends the output; a test feeds it directly.

Time. Every input carries its time on the agent's clock (``t``, seconds): in lock-step the world's sim time,
in real time the agent's monotonic clock. The estimator predicts over the measured interval between odometry
samples (every sample the driver delivered since the last step, in order), never over a count of steps or
scans; ``max_gap_s`` bounds one prediction (over a longer gap the rates are unknown: the base's own dead-reckoned
pose carries the estimate across it, where the sample has one).

Staleness, per stream, on the step's time:

- odometry older than ``odom_stale_s`` (or none yet): zero velocity (the estimate cannot follow the robot);
- a scan older than ``lidar_stale_s`` (or none yet): zero velocity for every policy that needs the lidar,
  which is every policy but one that is itself the situation-1 controller (PID): the decision layer's
  obstacle distance chooses between PID and the network, and the networks read the scans (Bai's o_z, Aina's
  and Chang's sectors, the Q-learning ranges). PID alone drives the same either way, so it goes on;
- fixes and neighbours' states have no staleness of their own: a neighbour silent for ``STALE_AFTER_S``
  leaves the formation logic (its body stays an obstacle to the lidar).

Scans. The policies that stack past scans (Bai's o_z: the last three) see them one control period apart at any
lidar rate: the step samples the newest scan once per period (a lidar slower than the period repeats its
newest, a faster one's scans in between are not stacked).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from ..comm.messages import Scan, State
from ..comm.radio import RadioModel, config_from_scenario
from ..estimation import EkfConfig, PoseEKF
from ..estimation.pose import Pose
from ..planning.runner import PlanRunner
from ..policies import make_policy
from .decision import DecisionLayer, Neighbour, obstacle_distance
from .frames import OdomFrame
from .guard import CollisionGuard, GuardConfig
from .quorum import Membership

log = logging.getLogger("stack.agent")

JUMP_TOLERANCE_M = 2.0  # a neighbour's state may move this much beyond what its v_max allows (estimate corrections)
STALE_AFTER_S = 3.0  # a neighbour not heard for this long is left out of the formation logic
N_SCANS = 3  # scans stacked for the policies (o_z)


@dataclass(frozen=True)
class OdomSample:
    """One odometry sample as the estimator takes it: rates measured up to time ``t`` (agent clock)."""

    v: float
    w: float
    t: float
    wz_imu: float | None = None  # gyro yaw rate with it, where the base has one
    pose: tuple[float, float, float] | None = None  # the base's dead-reckoned pose in its odom frame
    fix: tuple[float, float, float] | None = None  # the device's own position fix with it: (x, y, std), site frame


@dataclass(frozen=True)
class StepInputs:
    """Everything one control step reads."""

    step: int
    """Control step number (lock-step: the world's step)."""
    t: float
    """The step's time on the agent's clock [s] (lock-step: sim time; real time: monotonic)."""
    t_run: float
    """Time since the run began [s]: the formation schedule's clock."""
    now: float
    """The neighbours' stamp clock (lock-step: sim time; real time: UNIX seconds)."""
    odometry: tuple[OdomSample, ...] = ()
    """Odometry samples since the last step, oldest first."""
    scan: Scan | None = None
    """The newest scan (None: none yet)."""
    scan_t: float | None = None
    """When the newest scan arrived, agent clock."""
    fixes: tuple[tuple[float, float, float], ...] = ()
    """Absolute position fixes (x, y, std) in the site frame since the last step."""
    states: tuple[State, ...] = ()
    """Neighbours' states since the last step, in the order to offer them."""
    dead: frozenset[int] = frozenset()
    """Robots known to be gone."""
    held: str | None = None
    """Why this robot holds whatever the step decides (its session lost its routers: ``"no-network"``). The estimator
    runs on; who is gone, and so the roles, stay as they were; the command is zero."""
    goal: tuple[float, float] | None = None
    """A new goal for the mission (the ROS graph's goal topic), taken before the step (site frame)."""
    plans: tuple[int, ...] | None = None
    """Replay: the plans (tickets) the recorded step adopted (``stack.planning.runner``); None: the runner's own rule."""


@dataclass(frozen=True)
class StepOutput:
    """What one control step decided: the command ``(v, w)``, the estimated pose it came from, the situation
    (Bai's decision layer), the estimate's covariance trace, the distance to the goal, why the command is zero
    if it is (``stale``), and where the decision layer steers."""

    v: float
    w: float
    pose: Pose
    situation: str
    cov_trace: float
    d_goal: float | None
    stale: str | None  # why the command is zero: "odometry", "lidar", or None
    target: tuple[float, float] | None = None  # where the decision layer steers: the goal, the slot, an escape waypoint


HELD_BELOW = 0.02
"""[m/s] the guard holds a robot still when it lets less than this through of a command asking for more."""
SLIDE_K, SLIDE_W_MIN = 2.0, 0.3
"""The way out: turn rate [1/s] per radian still to turn, and the least turn rate [rad/s]."""


@dataclass
class StepConfig:
    """The step pipeline's settings (the robot and the scenario bring the rest)."""

    odom_stale_s: float = 0.5
    """Odometry older than this on the step's time: zero velocity."""
    lidar_stale_s: float = 0.5
    """A scan older than this: zero velocity, for the policies that need the lidar."""
    max_gap_s: float = 0.5
    """The longest interval between two odometry samples one prediction covers."""
    odom_origin: str = "site"
    """Where the odom frame is in the site frame: ``site``, ``boot``, ``boot-position`` or ``first``
    (``frames.OdomFrame``); the agent passes the robot's resolved ``RobotConfig.odom_origin``."""
    guard: GuardConfig = field(default_factory=GuardConfig)
    """The collision guard under every policy (``.guard``): the forward speed the robot can stop from."""


@dataclass
class StepCounters:
    fixes_used: int = 0
    rejected_states: int = 0
    odom_stale: int = 0
    lidar_stale: int = 0
    out_of_order: int = 0  # odometry samples older than the estimate (dropped)
    gaps_bridged: int = 0  # odometry gaps beyond max_gap_s carried by the base's own dead-reckoned pose
    noticed: dict[int, float] = field(default_factory=dict)  # robot id -> run time this agent dropped it


class StepPipeline:
    """One robot's estimator, radio model, neighbour table, decision layer and policy."""

    def __init__(self, scenario, robot_id: int, *, policy: str | None = None, seed: int | None = None,
                 config: StepConfig | None = None):
        self.sc = scenario
        self.robot = robot = scenario.robot(robot_id)
        self.id = robot_id
        self.cfg = config or StepConfig()
        seed = scenario.seed if seed is None else seed
        self.seed = seed
        self.role = robot.role or "peer"
        self.radio = RadioModel(config_from_scenario(scenario.comm, robot.comm_range, seed), robot_id)
        v_std, w_std = robot.odom_noise
        self.ekf_config = EkfConfig(odom_v_std=max(v_std, 0.02), odom_w_std=max(w_std, 0.02),
                                    gyro_std=max(robot.imu_noise, 0.01), fix_std=robot.fix[1] if robot.fix else 0.3)
        self.frame = OdomFrame(robot.pose, self.cfg.odom_origin)
        self.estimator = PoseEKF(*robot.pose, self.ekf_config)
        self._t_odom: float | None = None  # time of the newest odometry sample taken
        self._odom_pose: tuple[float, float, float] | None = None
        self.policy_name = policy or robot.policy
        self.policy_seed = seed * 1000 + robot_id
        self.planner = PlanRunner()  # inline; an agent hands it a runner beside the step (use_planner)
        self.policy = make_policy(self.policy_name, robot, seed=self.policy_seed)
        self.policy.planner = self.planner
        self.pid = make_policy("pid", replace(robot, role=self.role))  # situation 1 of the hybrid strategy
        self.decision = DecisionLayer(robot_id, self.role, scenario.formation, goal=robot.goal, radius=robot.radius,
                                      comm_range=robot.comm_range, scan_range=robot.lidar.range, dt=scenario.dt,
                                      centre_heading=self.policy.hybrid and self.policy.centre_heading and self.policy_name != "pid", fov=robot.lidar.fov,
                                      stuck=robot.stuck)
        self.decision.static_hold = self.policy.hybrid  # eq. (20)'s hold slows only the hybrid strategy's leader
        self.neighbours: dict[int, Neighbour] = {}
        self.scans: deque[np.ndarray] = deque(maxlen=N_SCANS)
        self.gone: set[int] = set()
        f = scenario.formation
        self.membership = Membership((r.id for r in scenario.robots), f.leader if f is not None else None)
        self.led_since: float | None = None
        self.drove_led: list[list[float]] = []  # [start, end] run times this robot drove as leader
        self.held_steps = 0  # steps held: the network (``StepInputs.held``) or no quorum
        self.counters = StepCounters()
        lid = robot.lidar
        self.guard = CollisionGuard(robot.radius, lid.fov, lid.beams, lid.range, self.cfg.guard)
        self._held_since: float | None = None  # step time since which the guard holds the robot still

    def use_planner(self, runner: PlanRunner) -> None:
        """Where the policy's plans run from now on (``stack.planning.runner``: a worker beside the step, or the
        replay's script)."""
        self.planner.close()
        self.planner = self.policy.planner = self.decision.stuck.runner = runner

    @property
    def needs_lidar(self) -> bool:
        """The policy says (``Policy.needs_lidar``): every one but ``pid``, which drives on the estimate alone."""
        return self.policy.needs_lidar

    # --- the step ------------------------------------------------------------------------------
    def step(self, inp: StepInputs) -> StepOutput:
        self.planner.begin(inp.step, inp.t, inp.plans)  # plans that are done and due are adopted first
        if inp.goal is not None:
            self.decision.set_goal(inp.goal)
        if inp.held is None:  # a robot that cannot hear keeps its peers: their tokens went with its own link
            self._note_gone(inp)
            self.membership.update(self.gone)
        self.estimate(inp)
        pose = self.estimator.pose
        self._neighbours(inp, pose)
        if inp.scan is not None:
            self.scans.append(np.asarray(inp.scan.ranges, dtype=float))  # once per period: o_z one period apart
        stale = self._stale(inp)
        v, w, situation, obs, target = 0.0, 0.0, "waiting", None, None
        if self.scans:
            dec = self._decide(inp, pose)
            situation, obs, target = dec.situation, dec.obs, dec.target
            held = self._held_why(inp)
            if held is not None:
                situation = held
                self.held_steps += 1
            elif dec.obs is not None and stale is None:
                v, w = self._guarded(*self._act(dec, inp.t_run), inp)
        self._note_led(inp.t_run, self.role == "leader" and situation not in ("no-network", "no-quorum", "no-world"))
        d_goal = float(obs.d_g) if situation == "peer" and obs is not None else None
        return StepOutput(v=v, w=w, pose=pose, situation=situation, cov_trace=self.estimator.cov_trace,
                          d_goal=d_goal, stale=stale, target=target)

    def _held_why(self, inp: StepInputs) -> str | None:
        """``"no-network"`` (the session lost its routers), ``"no-world"`` (a real robot before its mixed fleet's
        world runs), ``"no-quorum"`` (a leader whose side of a partition is not a quorum: ``quorum``), or None: the
        step drives."""
        if inp.held is not None:
            return inp.held
        if self.role == "leader" and not self.membership.quorum:
            return "no-quorum"
        return None

    def _note_led(self, t_run: float, driving: bool) -> None:
        """The run times this robot led (the leader's role, not held), joined where one step follows the next (the
        report's ``two_leaders_s`` overlaps the robots' lists)."""
        last = self.drove_led[-1] if self.drove_led else None
        if driving and last is not None and t_run - last[1] <= 1.5 * self.sc.dt:
            last[1] = t_run
        elif driving:
            self.drove_led.append([t_run, t_run])

    def estimate(self, inp: StepInputs) -> None:
        """Each odometry sample: its rates, then the motion over the interval since the previous one
        (eq. 1; see stack/estimation/ekf.py for the order), then its device fix; then the step's fixes."""
        ekf = self.estimator
        for s in inp.odometry:
            if self._t_odom is None:
                # the first sample: where the robot is, in the site frame. Its rates are those of the period
                # before it, which nothing predicts over; fused, they would leave the next period's rates
                # without the random walk of Q, and its measurement would be averaged with them (a leader that
                # turned from its first step kept half that step's turn as a yaw error for the whole run)
                ekf = self.estimator = PoseEKF(*self.frame.site_pose(s.pose), self.ekf_config)
            elif s.t < self._t_odom:
                self.counters.out_of_order += 1
                continue
            elif (bridge := self._bridge(s)) is not None:  # a gap the rates cannot cover: the base's own reckoning
                ekf.update_odometry(*bridge)
                ekf.predict(s.t - self._t_odom)
                self.counters.gaps_bridged += 1
            else:
                ekf.update_odometry(s.v, s.w)
                if s.wz_imu is not None:
                    ekf.update_gyro(s.wz_imu)
                ekf.predict(min(s.t - self._t_odom, self.cfg.max_gap_s))
            self._t_odom, self._odom_pose = s.t, s.pose
            if s.fix is not None:
                self._fix(*s.fix)
        for fx in inp.fixes:
            self._fix(*fx)

    def _bridge(self, s: OdomSample) -> tuple[float, float] | None:
        """Over a gap longer than ``max_gap_s`` (no odometry came: the network was down, the agent stalled), the
        rates (v, w) that carry the base's own dead-reckoned pose from the previous sample to this one (``pose``, its
        odom frame); None where the gap is short, a pose is missing, or the move is one the robot cannot make
        (its odom frame restarted)."""
        gap = s.t - self._t_odom
        a, b = self._odom_pose, s.pose
        if gap <= self.cfg.max_gap_s or a is None or b is None:
            return None
        dx, dy = b[0] - a[0], b[1] - a[1]
        forward = math.cos(a[2]) * dx + math.sin(a[2]) * dy
        dyaw = math.atan2(math.sin(b[2] - a[2]), math.cos(b[2] - a[2]))
        if math.hypot(dx, dy) > 1.5 * self.robot.v_max * gap + 0.05 or abs(dyaw) > 1.5 * self.robot.w_max * gap + 0.05:
            return None
        return forward / gap, dyaw / gap

    def _fix(self, x: float, y: float, std: float) -> None:
        if self.estimator.update_fix(x, y, std):
            self.counters.fixes_used += 1
            p = self.estimator.pose
            self.frame.refine((p.x, p.y, p.yaw), self._odom_pose)

    def _stale(self, inp: StepInputs) -> str | None:
        if self._t_odom is None or inp.t - self._t_odom > self.cfg.odom_stale_s:
            self.counters.odom_stale += 1
            return "odometry"
        if self.needs_lidar and (inp.scan_t is None or inp.t - inp.scan_t > self.cfg.lidar_stale_s):
            self.counters.lidar_stale += 1
            return "lidar"
        return None

    # --- neighbours ----------------------------------------------------------------------------
    def _note_gone(self, inp: StepInputs) -> None:
        dead = set(inp.dead) - {self.id}
        for rid in dead - self.gone:
            self.counters.noticed[rid] = inp.t_run
            log.info("agent %d: robot %d gone at t=%.1f s", self.id, rid, inp.t_run)
        for rid in self.gone - dead:
            log.info("agent %d: robot %d is back at t=%.1f s", self.id, rid, inp.t_run)
        self.gone = dead

    def _neighbours(self, inp: StepInputs, pose: Pose) -> None:
        """Neighbours through the radio model: range from their reported position to our estimate."""
        dead, now = self.gone, inp.now
        for m in inp.states:
            if m.id not in dead and m.id != self.id:
                self.radio.offer(m.id, (m.x, m.y), (pose.x, pose.y), m.stamp, m)
        for nid in dead & set(self.neighbours):
            del self.neighbours[nid]
        for m in self.radio.ready(now):
            if m.id in dead:
                continue
            old = self.neighbours.get(m.id)
            if old is not None and (m.stamp, m.seq) <= (old.stamp, old.seq):
                continue  # older than what we have (a restarted sender's seq starts again; its stamps do not)
            if old is not None and not self._plausible(old, m):
                self.counters.rejected_states += 1
                continue
            self.neighbours[m.id] = Neighbour(m.id, m.role, m.x, m.y, m.yaw, m.v, m.w, m.stamp, m.seq, m.d_goal)
        for nid in [i for i, n in self.neighbours.items() if now - n.stamp > STALE_AFTER_S]:
            del self.neighbours[nid]  # silent too long (frozen, or out of range): out of the formation logic,
            self.counters.noticed[nid] = inp.t_run  # and its body is an obstacle to the lidar like any other

    def _plausible(self, old: Neighbour, m: State) -> bool:
        """A state may not claim a jump faster than its robot can drive (plus room for estimate
        corrections): a teleport is a broken or hostile sender, dropped and counted."""
        try:
            v_max = self.sc.robot(m.id).v_max
        except Exception:  # noqa: BLE001 - an id outside the scenario: nothing to judge by
            v_max = self.robot.v_max
        dt = max(m.stamp - old.stamp, self.sc.dt)
        return math.hypot(m.x - old.x, m.y - old.y) <= 1.5 * v_max * dt + JUMP_TOLERANCE_M

    # --- decision and policy -------------------------------------------------------------------
    def _decide(self, inp: StepInputs, pose: Pose):
        scan = inp.scan
        ranges = self.scans[-1]
        if scan is not None:
            d_omin = obstacle_distance((pose.x, pose.y), pose.yaw, ranges, scan.angle_min, scan.angle_increment,
                                       scan.range_max, [n.predicted(inp.now) for n in self.neighbours.values()],
                                       self.robot.radius)
        else:
            d_omin = math.inf
        dec = self.decision.decide(pose, inp.now, self.neighbours, np.stack(self.scans), d_omin, t_run=inp.t_run,
                                   dead=self.gone)
        if self.decision.role != self.role:
            self._take_role(self.decision.role, inp.t_run)
        return dec

    def _tracks_plan(self, dec) -> bool:
        """Whether the PID tracker drives this step's planned detour (``robot.stuck.detour.tracker``)."""
        stuck = self.decision.stuck
        return dec.situation == "escape" and stuck.planned and stuck.cfg.detour.tracker == "pid"

    def _act(self, dec, t_run: float) -> tuple[float, float]:
        tracker = (not dec.use_network and self.policy.hybrid) or self._tracks_plan(dec)
        v, w = (self.pid if tracker else self.policy).act(dec.obs)  # a planned detour: the PID tracks its waypoints
        if self.role == "leader" and self.policy.hybrid:  # eq. (20), and a connectivity hold that gives up in time
            v = self.decision.hold_speed(v, dec.d_rmax, t_run, self.sc.formation.d_leader_slow,
                                         self.policy.leader_hold, self.robot.comm_range)
        return v, w

    def _guarded(self, v: float, w: float, inp: StepInputs) -> tuple[float, float]:
        """The collision guard on a command (a scan too old judges nothing: ``pid`` drives without one). A base that
        still rolls with something inside the margin ahead gets zero, both rates (``CollisionGuard.must_brake``). Held still
        ``slide_after_s`` while the policy asks to go forward, the robot takes the guard's way out instead: it turns
        in place to the nearest heading whose corridor is free, then drives along it (the guard judging that too)."""
        w = max(-self.robot.w_max, min(self.robot.w_max, w))  # the turn the base will make: the arc to judge
        if inp.scan_t is None or inp.t - inp.scan_t > self.cfg.lidar_stale_s:
            return v, w
        ranges, g = self.scans[-1], self.cfg.guard
        if inp.odometry and self.guard.must_brake(inp.odometry[-1].v, ranges, w):
            return 0.0, 0.0  # still rolling into the margin: brake straight, turn once stopped
        allowed = self.guard.limit(v, ranges, w)
        if not (v > HELD_BELOW and allowed < HELD_BELOW):
            self._held_since = None
            return allowed, w
        self._held_since = inp.t if self._held_since is None else self._held_since
        if g.slide_after_s <= 0 or inp.t - self._held_since < g.slide_after_s:
            return allowed, w
        theta = self.guard.way_out(ranges, prefer=w)
        if theta is None:
            return allowed, w
        self.guard.slides += 1
        if theta == 0.0:  # facing the way out: along it, as fast as the guard allows
            return self.guard.limit(v, ranges, 0.0), 0.0
        return 0.0, math.copysign(min(self.robot.w_max, max(SLIDE_W_MIN, SLIDE_K * abs(theta))), theta)

    def _take_role(self, role: str, t_run: float) -> None:
        """Failover: the formation's rule made this robot the leader (or a follower again)."""
        log.warning("agent %d: now %s at t=%.1f s", self.id, role, t_run)
        self.role = role
        if role == "leader" and self.led_since is None:
            self.led_since = t_run
        robot = replace(self.robot, role=role)
        self.policy = make_policy(self.policy_name, robot, seed=self.policy_seed)
        self.policy.planner = self.planner
        self.pid = make_policy("pid", robot)


__all__ = ["OdomSample", "StepConfig", "StepInputs", "StepOutput", "StepPipeline"]
