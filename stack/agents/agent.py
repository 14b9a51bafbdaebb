"""One robot's process: sensors in -> estimator -> decision layer -> policy -> driver out.

The loop runs once per control period. In lock-step (a simulated fleet run as fast as it
goes) a period is one world step: the agent waits for step k's odometry and scan and for
the states that its neighbours sent in step k-1, then answers with its command for step
k. In real time (a real robot, or ``stack-fleet run --realtime``) it ticks on its own
monotonic clock and uses the newest sensor data.

Every way out (SIGINT/SIGTERM, ``--steps``, an error) commands zero velocity first.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
import zenoh

from ..comm import Keys, MessageError, RadioModel, decode, encode, receive
from ..comm.messages import Answer, Clock, Diag, Fix, Scan, State, WorldStatus
from ..comm.radio import config_from_scenario
from ..drivers import Driver, DriverLimits, make_driver
from ..estimation import EkfConfig, PoseEKF
from ..policies import make_policy
from ..scenario import Scenario, fix_due
from .decision import DecisionLayer, Neighbour, obstacle_distance
from .lidar import scan_from_driver
from .timing import LatencyHistogram

log = logging.getLogger("stack.agent")

NEIGHBOUR_WAIT_S = 1.0  # lock-step: how long to wait for a neighbour's state of the previous step
JUMP_TOLERANCE_M = 2.0  # a neighbour's state may move this much beyond what its v_max allows (estimate corrections)
STALE_AFTER_S = 3.0  # a neighbour not heard for this long is left out of the formation logic
SENSOR_STALE_S = 0.5  # real time: no new scan and odometry for this long -> zero velocity
DEVICE_ODOM_WAIT_S = 0.05  # lock-step: how long (wall) a step waits for a device's odometry sample to catch up


@dataclass
class AgentConfig:
    """Everything one agent process needs; built by the CLI from flags and the scenario."""

    robot_id: int
    """This robot's id (``robots[].id`` in the scenario)."""
    scenario: Scenario
    """The validated scenario (already with the fleet's overrides applied)."""
    connect: str = "tcp/127.0.0.1:7447"
    """Zenoh endpoint of the router to join."""
    zenoh_config: str | None = None
    """A zenoh json5 file (``deploy/``: TLS, access control, a local router) layered under our settings."""
    allow_remote: bool = False
    """Allow a router endpoint off loopback (a multi-host fleet)."""
    fleet: str = "default"
    """Fleet name: the key prefix ``stack/<fleet>/``."""
    policy: str | None = None
    """Override the robot's policy."""
    driver: str | None = None
    """Override the robot's driver."""
    lockstep: bool = False
    """Answer the world's steps instead of ticking on the wall clock (simulation only)."""
    steps: int | None = None
    """Stop after this many control steps (tests); None runs until a signal."""
    seed: int | None = None
    """Seed of every random source of this agent; defaults to the scenario's."""
    sensor_timeout_s: float = 30.0
    """Lock-step: give up (zero, exit) if the world sends nothing for this long."""
    stop: threading.Event = field(default_factory=threading.Event)
    """Set to end the loop (signal handlers set it)."""


class Agent:
    def __init__(self, cfg: AgentConfig, session: zenoh.Session):
        self.cfg = cfg
        sc = cfg.scenario
        self.robot = sc.robot(cfg.robot_id)
        self.id = cfg.robot_id
        self.session = session
        self.keys = Keys(cfg.fleet)
        self.dt = sc.dt
        seed = sc.seed if cfg.seed is None else cfg.seed
        role = self.robot.role or "peer"
        self.role = role

        self.radio = RadioModel(config_from_scenario(sc.comm, self.robot.comm_range, seed), self.id)
        self.malformed: dict[str, int] = {}
        self.sent = 0
        self.seq = 0
        self.step = -1
        self.sim_now = 0.0
        self.hist = LatencyHistogram()
        self.state_latency = LatencyHistogram()
        self.fault = ""
        self._odo_step = -1
        self._odom_count = 0  # odometry samples the driver has delivered
        self._odom_used = 0  # ... of which the newest was in the last control step
        self._driver_fix = None  # the driver's newest position fix taken by the estimator
        self.device_odom_late = 0  # lock-step steps that went on without a new sample from the device
        self.sensor_stale = 0

        x, y, yaw = self.robot.pose
        v_std, w_std = self.robot.odom_noise
        self.ekf_config = EkfConfig(odom_v_std=max(v_std, 0.02), odom_w_std=max(w_std, 0.02),
                                    gyro_std=max(self.robot.imu_noise, 0.01),
                                    fix_std=self.robot.fix[1] if self.robot.fix else 0.3)
        self.estimator = PoseEKF(x, y, yaw, self.ekf_config)
        self._fix: Fix | None = None
        self.fixes_used = 0
        policy_name = self.policy_name = cfg.policy or self.robot.policy
        self.policy_seed = seed * 1000 + self.id
        self.policy = make_policy(policy_name, self.robot, seed=self.policy_seed)
        self.pid = make_policy("pid", replace(self.robot, role=role))  # situation 1 of the hybrid strategy
        self.decision = DecisionLayer(self.id, role, sc.formation, goal=self.robot.goal, radius=self.robot.radius,
                                      comm_range=self.robot.comm_range, scan_range=self.robot.lidar.range, dt=self.dt,
                                      centre_heading=self.policy.hybrid and policy_name != "pid")

        # sensor and neighbour inboxes, filled by zenoh callbacks
        self._cv = threading.Condition()
        self._scan: Scan | None = None
        self._driver_scan: tuple[object, Scan] | None = None  # (the driver's newest scan, it as our Scan)
        self.scans_from_driver = 0
        self._scan_arrival = 0.0
        self._odom_arrival = 0.0
        self._clocks: dict[int, Clock] = {}  # lock-step: the newest clocks by step (answered, dead)
        self._inbox: list[State] = []
        self._states_seen: dict[int, int] = {}  # sender -> newest step seen on the wire
        self._awaited: set[int] = set()  # lock-step: senders whose state of _awaited_step we wait for
        self._awaited_step = -1
        self._dead: set[int] = set()  # real time: robots whose liveliness token is gone
        self.gone: set[int] = set()  # robots this agent has dropped (lock-step: the world's Clock.dead)
        self.noticed: dict[int, float] = {}  # robot id -> run time at which this agent last dropped it (gone or stale)
        self.led_since: float | None = None  # failover: run time this agent took over as leader
        self.rejected_states = 0  # neighbours' states that claimed an impossible jump
        self.neighbour_waits_timed_out = 0  # lock-step: steps that went on without an awaited neighbour state
        self.neighbours: dict[int, Neighbour] = {}
        self.scans: deque[np.ndarray] = deque(maxlen=3)

        limits = DriverLimits(self.robot.v_max, self.robot.w_max, self.robot.cmd_timeout)
        driver_name = cfg.driver or self.robot.driver
        clock = (lambda: self.sim_now) if cfg.lockstep else time.monotonic
        params = self.robot.driver_params.get(driver_name, {})
        self.driver: Driver = make_driver(driver_name, self.id, limits, session=session, keys=self.keys,
                                          stamp=self._stamp, on_malformed=self._count_malformed,
                                          on_odom=self._on_odom, clock=clock, **params)

    # --- time ----------------------------------------------------------------------
    def _stamp(self) -> float:
        return self.sim_now if self.cfg.lockstep else time.time()

    # --- callbacks (zenoh threads) -------------------------------------------------
    def _count_malformed(self, key: str) -> None:
        topic = key.rsplit("/", 1)[-1]
        with self._cv:
            self.malformed[topic] = self.malformed.get(topic, 0) + 1

    def _on_odom(self, _odo) -> None:
        with self._cv:
            self._odom_arrival = time.perf_counter()
            self._odom_count += 1
            self._cv.notify_all()

    def _on_scan(self, sample: zenoh.Sample) -> None:
        try:
            m = decode(sample.payload.to_bytes(), Scan)
            if m.id != self.id:
                raise MessageError("scan for another robot")
            if len(m.ranges) != self.robot.lidar.beams or m.range_max > self.robot.lidar.range + 1e-6:
                raise MessageError("scan does not match this robot's lidar")
        except MessageError:
            self._count_malformed(str(sample.key_expr))
            return
        with self._cv:
            self._scan = m
            self._scan_arrival = time.perf_counter()
            self._cv.notify_all()

    def _on_fix(self, sample: zenoh.Sample) -> None:
        m = receive(sample, Fix, self._count_malformed)
        if m is None:
            return
        if m.id != self.id:
            self._count_malformed(str(sample.key_expr))
            return
        with self._cv:
            self._fix = m

    def _on_clock(self, sample: zenoh.Sample) -> None:
        m = receive(sample, Clock, self._count_malformed)
        if m is None:
            return
        with self._cv:
            self._clocks[m.step] = m
            for old in [s for s in self._clocks if s < m.step - 5]:
                del self._clocks[old]
            if self.cfg.lockstep:
                self.sim_now = max(self.sim_now, m.t)
            self._cv.notify_all()

    def _on_world_status(self, sample: zenoh.Sample) -> None:
        m = receive(sample, WorldStatus, self._count_malformed)
        if m is not None and m.state == "done" and self.cfg.lockstep:
            log.info("agent %d: the world is done (%s): stopping", self.id, m.why)
            self.cfg.stop.set()  # a simulated run is over: zero velocity and exit, also when nobody signals us

    def _on_state(self, sample: zenoh.Sample) -> None:
        sender = Keys.id_of(str(sample.key_expr))
        if sender == self.id:
            return
        try:
            m = decode(sample.payload.to_bytes(), State)
            if sender is None or m.id != sender:
                raise MessageError("state id does not match its key")
        except MessageError:
            self._count_malformed(str(sample.key_expr))
            return
        if m.wall is not None:
            self.state_latency.add((time.time() - m.wall) * 1000.0)
        with self._cv:
            self._inbox.append(m)
            self._states_seen[m.id] = max(self._states_seen.get(m.id, -1), m.step)
            awaited = self._awaited
            if awaited and m.id in awaited and m.step >= self._awaited_step:
                awaited.discard(m.id)
                if not awaited:  # wake the loop once, when the last awaited state is in
                    self._cv.notify_all()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        rid = Keys.id_of(str(sample.key_expr))
        if rid is None or rid == self.id:
            return
        with self._cv:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._dead.add(rid)  # the loop drops it from its neighbours (only the loop touches them)
                log.info("agent %d: robot %d left (liveliness lost)", self.id, rid)
            else:
                self._dead.discard(rid)

    # --- main loop -------------------------------------------------------------------
    def run(self) -> int:
        k = self.keys
        s = self.session
        self._state_pub = s.declare_publisher(k.robot(self.id, "state"), congestion_control=zenoh.CongestionControl.BLOCK)
        self._diag_pub = s.declare_publisher(k.robot(self.id, "diag"), congestion_control=zenoh.CongestionControl.BLOCK)
        self._answer_pub = s.declare_publisher(k.robot(self.id, "answer"), congestion_control=zenoh.CongestionControl.BLOCK)
        subs = [
            s.declare_subscriber(k.robot(self.id, "scan"), self._on_scan),
            s.declare_subscriber(k.robot(self.id, "fix"), self._on_fix),
            s.declare_subscriber(k.all_robots("state"), self._on_state),
            s.declare_subscriber(k.world("clock"), self._on_clock),
            s.declare_subscriber(k.world("status"), self._on_world_status),
            s.liveliness().declare_subscriber(k.all_alive, self._on_alive, history=True),
        ]
        token = None
        try:
            with self.driver:
                token = s.liveliness().declare_token(k.alive(self.id))
                log.info("agent %d (%s, policy %s, driver %s) up on %s", self.id, self.role, self.policy.name,
                         self.driver.name, self.cfg.connect)
                log.info("agent %d robot config: %s", self.id, self.robot)
                log.info("agent %d estimator config: %s", self.id, self.ekf_config)
                try:
                    self._loop()
                finally:
                    self.driver.stop()  # zero velocity before anything else on the way out
                    self._publish_diag("stopped")
        finally:
            if token is not None:
                token.undeclare()
            for sub in subs:
                sub.undeclare()
        return 0

    def _loop(self) -> None:
        stop = self.cfg.stop
        steps = 0
        while not stop.is_set():
            k = self._wait_sensors()
            if k is None:
                continue
            self._control_step()
            steps += 1
            if self.cfg.steps is not None and steps >= self.cfg.steps:
                break

    def _wait_sensors(self) -> int | None:
        """Block until a new step's odometry and scan are in (the sensors set the loop's period).

        Lock-step: also wait (bounded) for the states that the robots which commanded step k-1
        sent before their command, so every agent sees the same messages. Real time: sensors
        older than ``SENSOR_STALE_S`` stop the robot (zero) until they come back.
        """
        lockstep = self.cfg.lockstep
        limit = self.cfg.sensor_timeout_s if lockstep else SENSOR_STALE_S
        deadline = time.monotonic() + limit
        with self._cv:
            while True:
                if self.cfg.stop.is_set():
                    return None
                scan, odo = self._current_scan(), self.driver.read()
                if scan is not None and odo is not None and scan.step > self.step and self._odometry_of(scan, odo) \
                        and (not lockstep or self._complete(scan.step, odo)):
                    break
                if time.monotonic() > deadline:
                    if lockstep:
                        raise TimeoutError(f"agent {self.id}: no sensor data from the world for {limit:.0f} s")
                    if self.driver.last_sent != (0.0, 0.0):
                        log.warning("agent %d: sensors stale for %.1f s: zero velocity", self.id, limit)
                        self.driver.stop()
                        self.sensor_stale += 1
                    return None
                self._cv.wait(0.05)
            k = scan.step
            clock = self._clocks.get(k)
            if lockstep and clock is not None and self.step >= 0:  # a (re)started agent has nobody to wait for
                self._awaited_step = k - 1
                self._awaited = {i for i in clock.answered if i != self.id and i not in clock.dead
                                 and self._states_seen.get(i, -1) < k - 1}
                t_end = time.monotonic() + NEIGHBOUR_WAIT_S
                while self._awaited and time.monotonic() < t_end:
                    if self.cfg.stop.is_set():
                        return None
                    self._cv.wait(0.05)
                if self._awaited:  # a sender answered the world but its state never reached us: go on, say so
                    self.neighbour_waits_timed_out += 1
                    log.warning("agent %d: step %d: no state of step %d from %s within %.1f s; going on without",
                                self.id, k, k - 1, sorted(self._awaited), NEIGHBOUR_WAIT_S)
                self._awaited = set()
            if lockstep:
                self.sim_now = max(self.sim_now, scan.stamp)
            return k

    def _current_scan(self) -> Scan | None:
        """The newest scan: the world's (simulation, and every lock-step run), or in real time the robot's
        own, where its driver reads one (a Jackal's ``LaserScan``: swap the driver, nothing else)."""
        if self.cfg.lockstep or not self.driver.provides_scan:
            return self._scan
        data = self.driver.read_scan()
        if data is None:
            return None
        if self._driver_scan is None or self._driver_scan[0] is not data:
            step = self._driver_scan[1].step + 1 if self._driver_scan is not None else 0
            self._driver_scan = (data, scan_from_driver(self.robot, data, step))
            self.scans_from_driver += 1
            self._scan_arrival = time.perf_counter()
        return self._driver_scan[1]

    def _odometry_of(self, scan: Scan, odo) -> bool:
        """Is ``odo`` the odometry to go with ``scan``? A simulated base's carries the step; a device's
        (CAN encoders, a rover's telemetry, a bridged base's odometry topic) does not: in lock-step the
        world sent it just before the step's sensors, so we give it a moment to arrive (bounded:
        a device that skipped a sample must not stall the fleet), and in real time the newest will do."""
        if odo.step >= 0:
            return odo.step == scan.step
        if not self.cfg.lockstep:
            return True
        return self._odom_count > self._odom_used or time.perf_counter() - self._scan_arrival > DEVICE_ODOM_WAIT_S

    def _complete(self, k: int, odo) -> bool:
        """Lock-step: step k's gyro rate and (when one is due) position fix are in too; zenoh keeps
        order per key, not across keys, so waiting on the scan alone would race."""
        if self.driver.has_imu and odo.wz_imu is None:
            return False
        if k not in self._clocks:  # its answered and dead lists
            return False
        if fix_due(self.robot, k, self.dt):
            return self._fix is not None and self._fix.step == k
        return True

    def _control_step(self) -> None:
        with self._cv:
            scan = self._current_scan()
            odo = self.driver.read()
            if odo.step < 0 and self.cfg.lockstep and self._odom_count == self._odom_used and self.step >= 0:
                self.device_odom_late += 1
            self._odom_used = self._odom_count
            fix, self._fix = self._fix, None
            t_sensor = max(self._scan_arrival, self._odom_arrival)
            k = scan.step
            now = self.sim_now if self.cfg.lockstep else time.time()
            # lock-step: only states sent before this step are offered, in a fixed order (determinism)
            if self.cfg.lockstep:
                take = sorted((m for m in self._inbox if m.step < k), key=lambda m: (m.step, m.id, m.seq))
                self._inbox = [m for m in self._inbox if m.step >= k]
            else:
                take, self._inbox = self._inbox, []
            clock = self._clocks.get(k)
            # who is gone: in lock-step the world's list of step k (every agent drops a robot at the same
            # step); in real time our own liveliness subscription
            dead = set(clock.dead) if self.cfg.lockstep and clock is not None else set(self._dead)
        dead.discard(self.id)
        t_run = k * self.dt
        if odo.step < 0:  # a device's odometry: the newest, for this step
            odo = replace(odo, step=k)
        if self.driver.fault and not self.fault:
            self.fault = f"{self.driver.name} driver: {self.driver.fault}"
            log.error("agent %d: %s: the robot is stopped (zero velocity) from t=%.1f s", self.id, self.fault, t_run)
            self._publish_diag("fault")
        for rid in dead - self.gone:
            self.noticed[rid] = t_run
            log.info("agent %d: robot %d gone at t=%.1f s", self.id, rid, t_run)
        for rid in self.gone - dead:
            log.info("agent %d: robot %d is back at t=%.1f s", self.id, rid, t_run)
        self.gone = dead
        first = self.step < 0
        self.step = k

        # estimator (filterpy EKF): the rates measured over the period just ended, then the motion
        # over it (eq. 1), then an absolute fix if one came (see stack/estimation/ekf.py for the order)
        if first and odo.pose is not None:
            # (re)start: the estimate begins where the base's own odometry says it is (after a restart
            # mid-run that is not the scenario's start pose)
            self.estimator = PoseEKF(*odo.pose, self.ekf_config)
        ekf = self.estimator
        if odo.step > self._odo_step:
            n = 1 if self._odo_step < 0 else min(odo.step - self._odo_step, 5)
            ekf.update_odometry(odo.v, odo.w)
            if odo.wz_imu is not None:
                ekf.update_gyro(odo.wz_imu)
            ekf.predict(n * self.dt)
            self._odo_step = odo.step
        if fix is not None:
            if ekf.update_fix(fix.x, fix.y, fix.std):
                self.fixes_used += 1
        dfix = self.driver.position_fix()  # e.g. a rover autopilot's own position estimate (LOCAL_POSITION_NED)
        if dfix is not None and dfix is not self._driver_fix:
            self._driver_fix = dfix
            if ekf.update_fix(dfix[0], dfix[1], dfix[2]):
                self.fixes_used += 1
        pose = ekf.pose

        # neighbours through the radio model: range from their reported position to our estimate
        for m in take:
            if m.id in dead:
                continue
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
                self.rejected_states += 1
                continue
            self.neighbours[m.id] = Neighbour(m.id, m.role, m.x, m.y, m.yaw, m.v, m.w, m.stamp, m.seq, m.d_goal)
        for nid in [i for i, n in self.neighbours.items() if now - n.stamp > STALE_AFTER_S]:
            del self.neighbours[nid]  # silent too long (frozen, or out of range): out of the formation logic,
            self.noticed[nid] = t_run  # and its body is an obstacle to the lidar like any other

        ranges = np.asarray(scan.ranges, dtype=float)
        self.scans.append(ranges)
        scans = np.stack(self.scans)
        d_omin = obstacle_distance((pose.x, pose.y), pose.yaw, ranges, scan.angle_min, scan.angle_increment,
                                   scan.range_max, [n.predicted(now) for n in self.neighbours.values()],
                                   self.robot.radius)
        dec = self.decision.decide(pose, now, self.neighbours, scans, d_omin, t_run=t_run, dead=dead)
        if self.decision.role != self.role:
            self._take_role(self.decision.role, t_run)
        if dec.obs is None:
            v, w = 0.0, 0.0
        else:
            v, w = (self.policy if dec.use_network or not self.policy.hybrid else self.pid).act(dec.obs)
            if self.role == "leader" and self.policy.hybrid:
                v = DecisionLayer.leader_speed(v, dec.d_rmax, self.cfg.scenario.formation.d_leader_slow,  # eq. (20)
                                               self.policy.leader_hold, self.robot.comm_range)

        self.seq += 1
        st = State(id=self.id, role=self.role, seq=self.seq, stamp=self._stamp(), x=pose.x, y=pose.y, yaw=pose.yaw,
                   v=pose.v, w=pose.w, step=k, situation=dec.situation, wall=time.time(),
                   cov_trace=ekf.cov_trace,
                   d_goal=float(dec.obs.d_g) if dec.situation == "peer" and dec.obs is not None else None)
        self._state_pub.put(encode(st))
        self.sent += 1
        self.driver.command(v, w, step=k)
        if self.cfg.lockstep and not self.driver.answers_steps:  # the command went over the device's wire
            self._answer_pub.put(encode(Answer(id=self.id, step=k, stamp=self._stamp())))
        self.hist.add((time.perf_counter() - t_sensor) * 1000.0)
        if k % 10 == 0:
            self._publish_diag("running")

    def _plausible(self, old: Neighbour, m: State) -> bool:
        """A state may not claim a jump faster than its robot can drive (plus room for estimate
        corrections): a teleport is a broken or hostile sender, dropped and counted."""
        try:
            v_max = self.cfg.scenario.robot(m.id).v_max
        except Exception:  # noqa: BLE001 - an id outside the scenario: nothing to judge by
            v_max = self.robot.v_max
        dt = max(m.stamp - old.stamp, self.dt)
        return math.hypot(m.x - old.x, m.y - old.y) <= 1.5 * v_max * dt + JUMP_TOLERANCE_M

    def _take_role(self, role: str, t_run: float) -> None:
        """Failover: the formation's rule made this robot the leader (or a follower again)."""
        log.warning("agent %d: now %s at t=%.1f s", self.id, role, t_run)
        self.role = role
        if role == "leader" and self.led_since is None:
            self.led_since = t_run
        robot = replace(self.robot, role=role)
        self.policy = make_policy(self.policy_name, robot, seed=self.policy_seed)
        self.pid = make_policy("pid", robot)

    def _publish_diag(self, state: str) -> None:
        c = self.radio.counters
        with self._cv:
            malformed = dict(self.malformed)
        d = Diag(id=self.id, stamp=self._stamp(), step=self.step, state=state, sent=self.sent, received=c.received,
                 delivered=c.delivered, dropped_loss=c.dropped_loss, dropped_range=c.dropped_range,
                 malformed=sum(malformed.values()), malformed_by_key=malformed, loop_hist=self.hist.as_dict(),
                 state_latency_hist=self.state_latency.as_dict(),
                 situations={k: v for k, v in self.decision.counts.items() if v}, fixes_used=self.fixes_used,
                 fixes_rejected=self.estimator.rejected_fixes, inputs_rejected=self.estimator.rejected_nan,
                 sensor_stale=self.sensor_stale,
                 fault=self.fault, noticed=dict(self.noticed), led_since=self.led_since,
                 rejected_states=self.rejected_states, neighbour_waits_timed_out=self.neighbour_waits_timed_out,
                 device_odom_late=self.device_odom_late, scans_from_driver=self.scans_from_driver,
                 shield_masked=getattr(self.policy, "masked", None))
        self._diag_pub.put(encode(d))
