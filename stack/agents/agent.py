"""One robot's process: sensors in -> step pipeline (estimator, decision layer, policy) -> driver out.

The control step itself is ``step.StepPipeline`` (no Zenoh, no barrier); this module gathers its inputs and
sends its output. Two ways to run:

- Lock-step (a simulated fleet run as fast as it goes): the world's clock drives everything. Step k's inputs
  are complete when ``stack.comm.lockstep.StepBarrier`` says so (step k's clock, scan, gyro, due fix, the
  driver's sample of k or the device's samples of k); the states its neighbours sent in k-1 come in clock k
  (``StateRelay``: no subscription per sender); every time is the world's sim time, so the run is the same
  every time.
- Real time (a real robot, or ``stack-fleet run --realtime``): the loop ticks on the agent's own period (the
  scenario's ``dt``) on its monotonic clock. Each stream arrives at its own rate: every odometry sample the
  driver delivers is queued with its time (``frames.StreamClock``: device stamps where usable, arrival
  otherwise), the newest scan and the fixes since the last tick are taken. Run time comes from the world's
  clock where one is heard (a simulated real-time run), from the agent's own start otherwise.

Every way out (SIGINT/SIGTERM, ``--steps``, an error) commands zero velocity first.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace

import zenoh

from ..comm import Keys, MessageError, decode, encode, receive
from ..comm.link import GoneJudge, LinkWatch
from ..comm.lockstep import StepBarrier
from ..comm.messages import Answer, Clock, Diag, Fix, Relayed, Scan, State, WorldStatus
from ..drivers import Driver, DriverLimits, make_driver
from ..drivers.lidar import Lidar, make_lidar
from ..planning.runner import ThreadRunner
from ..scenario import Scenario, fix_due
from .frames import StreamClock
from .lidar import scan_from_driver, scan_from_lidar
from .virtual import VirtualReturns
from .ros_graph import RosGraphLink, open_ros_graph
from .guard import GuardConfig
from .step import OdomSample, StepConfig, StepInputs, StepOutput, StepPipeline
from .steplog import WHAT as STEP_IO, StepLogger
from .timing import LatencyHistogram

log = logging.getLogger("stack.agent")

DEVICE_ODOM_WAIT_S = 2.0  # lock-step: how long (wall) to wait for a device sample the world says it sent (a lost one)
STEP_LOG_BUFFER = 64 * 1024  # bytes of step records held before a write (a killed agent loses at most this)
PLAN_LOCKSTEP_STEPS = 1  # lock-step: a plan asked for at step k drives from step k + this
ODOM_QUEUE = 1000  # odometry samples kept between two control steps (a stalled loop drops the oldest)


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
    odom_origin: str | None = None
    """Where the driver's odom frame is in the site frame (``frames.OdomFrame``): ``site``, ``boot`` (odom (0, 0, 0)
    is the start pose: the device booted there; right after a restart too), ``boot-position`` (origin at the start
    position, headings the site's: an ArduPilot EKF origin) or ``first`` (the first sample is at the start pose;
    fresh starts only). None: the robot's own, resolved from the scenario (``RobotConfig.odom_origin``)."""
    record: str | None = None
    """Record this robot's own view to this MCAP file (``stack.agents.view``; the ``viz`` extra)."""
    viz: str | None = None
    """Serve this robot's own view live (Foxglove WebSocket) on this ``tcp/HOST:PORT``."""
    log_steps: bool = False
    """Publish every step's inputs and outputs (``steplog``, the neighbours' states by name) on
    ``stack/<fleet>/<id>/step_io``, for a recorder elsewhere (``python -m stack.fleet.record``); ``record`` keeps
    them in the robot's own file in any case."""
    step_log: str | None = None
    """Append every step's record (as ``log_steps`` publishes it) to this file, one JSON line a step: how a
    recording ``stack-fleet run`` gets its agents' steps into ``run.mcap`` (its recorder reads the files at the
    end; over Zenoh, 32 robots' records cost the lock-step fleet 25-45 % of its speed: docs/replay.md)."""
    stop: threading.Event = field(default_factory=threading.Event)
    """Set to end the loop (signal handlers set it)."""


@dataclass
class _Inbox:
    """What the zenoh callbacks collected since the last step (guarded by the agent's condition)."""

    odometry: deque = field(default_factory=lambda: deque(maxlen=ODOM_QUEUE))  # (Odometry, fix, t real time)
    odom_raw: object = None  # the newest sample as the driver delivered it
    fixes: list = field(default_factory=list)  # Fix messages of the world
    states: list = field(default_factory=list)
    scan: Scan | None = None
    scan_t: float | None = None  # agent clock
    driver_scan: tuple | None = None  # (the driver's newest scan, it as our Scan)
    lidar_n: int = 0  # scans the robot's own lidar source delivered
    dead: set = field(default_factory=set)  # real time: robots whose liveliness token is gone
    world_clock: tuple[float, float] | None = None  # real time: (the world's t, our clock when it came)
    sensor_perf: float = 0.0  # perf_counter of the newest sensor message (loop latency)


class Agent:
    def __init__(self, cfg: AgentConfig, session: zenoh.Session):
        self.cfg = cfg
        sc = cfg.scenario
        self.robot = sc.robot(cfg.robot_id)
        self.id = cfg.robot_id
        self.session = session
        self.keys = Keys(cfg.fleet)
        self.dt = sc.dt
        self.pipeline = StepPipeline(sc, self.id, policy=cfg.policy, seed=cfg.seed,
                                     config=StepConfig(odom_origin=cfg.odom_origin or self.robot.odom_origin,
                                                       guard=self.robot.guard or GuardConfig()))
        # plans beside the step: lock-step adopts one at the next step (the same to the bit on any machine), real
        # time once it is done (the step log says when: it replays)
        self.pipeline.use_planner(ThreadRunner(lockstep_steps=PLAN_LOCKSTEP_STEPS if cfg.lockstep else None))
        self.malformed: dict[str, int] = {}
        self.sent = 0
        self.seq = 0
        self.step = -1
        self.sim_now = 0.0
        self.hist = LatencyHistogram()  # newest sensor message -> command (includes waiting for the tick)
        self.compute = LatencyHistogram()  # the agent's own work a step: tick (or barrier) -> command sent
        self.state_latency = LatencyHistogram()
        self.fault = ""
        self.sensor_stale = 0  # times the robot was stopped because a stream went stale
        self.scans_from_driver = 0
        self.odom_redelivered = 0  # older odometry samples a driver handed over after a newer one (dropped)
        self._stale: str | None = None
        self._mono0 = time.monotonic()
        self._odom_clock = StreamClock()
        self._cv = threading.Condition()
        self._in = _Inbox()
        # the neighbours' states of step k-1 come in clock k (the world waited for them: StateRelay), so a state
        # the clock lacks is late at once (counted), to come in a later clock
        self.barrier = StepBarrier(self.id, self._cv, neighbour_wait_s=0.0,
                                   device_wait_s=DEVICE_ODOM_WAIT_S, sensor_timeout_s=cfg.sensor_timeout_s)
        self.driver: Driver = self._make_driver()
        self.ros_graph: RosGraphLink | None = None  # robot.ros_graph: opened by run() where enabled
        self.lidar: Lidar | None = self._make_lidar()
        # a real robot's view of the virtual ones (robot.lidar.virtual): the world's virtual returns, merged
        self.virtual = VirtualReturns(self.robot) if self.robot.embodiment == "real" and self.robot.lidar.virtual else None
        # a real robot in a fleet with simulated robots holds (its estimate still published) until the world runs
        self._await_world = self.robot.embodiment == "real" and any(r.embodiment == "simulated" for r in sc.robots)
        self._lidar_sync: tuple[int, int] | None = None  # lock-step: (device scans, scans we had) at our first step
        self._lidar_wait: tuple[int, float] | None = None  # lock-step: (step, wall deadline) of a wait for scans
        self._lidar_taken = (0, None)  # lock-step: (lidar_n, sim time) when a new scan was last taken
        self.lidar_late = 0  # lock-step steps that went on without all of the lidar's scans
        self.view = None  # this robot's own recording / live view (``view.AgentView``), when asked for
        self.steplog: StepLogger | None = None  # every step's inputs and outputs for our own recording (``steplog``)
        self.steplog_fleet: StepLogger | None = None  # ... for the fleet's (published / a file): states by name
        self._step_pub = None
        self._step_file = None
        # real time: our session's link to its router(s), and the peers' tokens judged by it (``stack.comm.link``)
        self.link = LinkWatch(session, clock=self._now)
        self.judge = GoneJudge(self.link)

    @property
    def role(self) -> str:
        return self.pipeline.role

    @property
    def estimator(self):
        return self.pipeline.estimator

    def _make_driver(self) -> Driver:
        limits = DriverLimits(self.robot.v_max, self.robot.w_max, self.robot.cmd_timeout)
        name = self.cfg.driver or self.robot.driver
        clock = (lambda: self.sim_now) if self.cfg.lockstep else time.monotonic
        params = self.robot.driver_params.get(name, {})
        return make_driver(name, self.id, limits, session=self.session, keys=self.keys, stamp=self._stamp,
                           on_malformed=self._count_malformed, on_odom=self._on_odom, clock=clock, **params)

    def _make_lidar(self) -> Lidar | None:
        """The robot's own lidar source (``robot.lidar.source``); None: the world's scans (``_on_scan``)."""
        source = self.robot.lidar.source
        if source == "world":
            return None
        clock = (lambda: self.sim_now) if self.cfg.lockstep else time.monotonic
        return make_lidar(source, self.id, session=self.session, keys=self.keys, clock=clock, on_scan=self._on_lidar,
                          on_malformed=self._count_malformed, **self.robot.lidar.params)

    # --- time ----------------------------------------------------------------------
    def _stamp(self) -> float:
        return self.sim_now if self.cfg.lockstep else time.time()

    def _now(self) -> float:
        """The agent's own clock: monotonic seconds since the agent started."""
        return time.monotonic() - self._mono0

    # --- callbacks (zenoh and driver threads) -------------------------------------------
    def _count_malformed(self, key: str) -> None:
        topic = key.rsplit("/", 1)[-1]
        with self._cv:
            self.malformed[topic] = self.malformed.get(topic, 0) + 1

    def _on_odom(self, odo) -> None:
        """Every sample the driver delivers, queued with its device fix and its time on our clock. A base whose
        gyro comes separately (``sim``) delivers a sample twice (the same object): the second time paired with
        its gyro rate, which replaces the first."""
        driver = getattr(self, "driver", None)
        raw, fix = odo, None
        if driver is not None:
            if driver.has_imu:
                paired = driver.read()
                if paired is not None and (paired.stamp, paired.step) == (odo.stamp, odo.step):
                    odo = paired
            dfix = driver.position_fix()  # the driver's thread set it with this sample
            fix = None if dfix is None else (dfix[0], dfix[1], dfix[2])
        arrival = self._now()
        with self._cv:
            q, last = self._in.odometry, self._in.odom_raw
            if last is not None and raw is not last and 0 <= raw.step < last.step:
                self.odom_redelivered += 1  # an older step's sample handed over late: never the newest
                if self.odom_redelivered == 1:
                    log.warning("agent %d: odometry of step %d handed over after step %d's: dropped (counted in "
                                "odom_redelivered)", self.id, raw.step, last.step)
            elif raw is last:  # the same sample again: keep the one with the gyro rate
                if q and odo.wz_imu is not None and q[-1][0].wz_imu is None and q[-1][0].step == odo.step:
                    q[-1] = (odo, fix, q[-1][2])
            else:
                t = self._odom_clock.time_of(odo.stamp, arrival) if not self.cfg.lockstep else arrival
                q.append((odo, fix, t))
                self._in.odom_raw = raw
            self._in.sensor_perf = time.perf_counter()
            self._cv.notify_all()

    def _on_scan(self, sample: zenoh.Sample) -> None:
        try:
            m = self._own_scan(decode(sample.payload.to_bytes(), Scan))
        except MessageError:
            self._count_malformed(str(sample.key_expr))
            return
        with self._cv:
            self._in.scan, self._in.scan_t = m, self._now()
            self._in.sensor_perf = time.perf_counter()
            self._cv.notify_all()

    def _on_virtual_scan(self, sample: zenoh.Sample) -> None:
        try:
            self.virtual.accept(decode(sample.payload.to_bytes(), Scan), self._now())
        except (MessageError, ValueError):
            self._count_malformed(str(sample.key_expr))

    def _own_scan(self, m: Scan) -> Scan:
        if m.id != self.id:
            raise MessageError("scan for another robot")
        if len(m.ranges) != self.robot.lidar.beams or m.range_max > self.robot.lidar.range + 1e-6:
            raise MessageError("scan does not match this robot's lidar")
        return m

    def _on_lidar(self, data) -> None:
        """Each scan of the robot's own lidar (its source's thread), as this robot's configured ``Scan``."""
        with self._cv:
            n = self._in.lidar_n
        scan = scan_from_lidar(self.robot, data, n, self._stamp())
        with self._cv:
            self._in.scan, self._in.scan_t, self._in.lidar_n = scan, self._now(), n + 1
            self.scans_from_driver += 1
            self._in.sensor_perf = time.perf_counter()
            self._cv.notify_all()

    def _on_fix(self, sample: zenoh.Sample) -> None:
        m = receive(sample, Fix, self._count_malformed)
        if m is None:
            return
        if m.id != self.id:
            self._count_malformed(str(sample.key_expr))
            return
        with self._cv:
            self._in.fixes.append(m)
            self._cv.notify_all()

    def _on_clock(self, sample: zenoh.Sample) -> None:
        m = receive(sample, Clock, self._count_malformed)
        if m is None:
            return
        states = [st for st in map(self._heard_state, m.states) if st is not None] if self.cfg.lockstep else []
        with self._cv:
            for st in states:  # the neighbours' states of step k-1, relayed by the world (StateRelay)
                self._in.states.append(st)
                self.barrier.on_state(st.id, st.step)
            if self.cfg.lockstep:  # sim_now (the driver's clock) moves when the step is taken, not here
                self.barrier.on_clock(m)
            else:
                self._in.world_clock = (m.t, self._now())
                for rid in m.dead:
                    self._in.dead.add(rid)

    def _on_world_status(self, sample: zenoh.Sample) -> None:
        m = receive(sample, WorldStatus, self._count_malformed)
        if m is not None and m.state == "done" and self.cfg.lockstep:
            log.info("agent %d: the world is done (%s): stopping", self.id, m.why)
            self.cfg.stop.set()  # a simulated run is over: zero velocity and exit, also when nobody signals us

    def _on_state(self, sample: zenoh.Sample) -> None:
        """Real time: each neighbour's state on its own key."""
        m = self._heard_state(sample)
        if m is not None:
            with self._cv:
                self._in.states.append(m)
                self.barrier.on_state(m.id, m.step)

    def _heard_state(self, heard) -> State | None:
        """A neighbour's state, from its key (a zenoh sample) or relayed by the world in lock-step (``Relayed``):
        decoded, validated and counted by its key the same way; None for our own or a malformed one."""
        key = heard.key if isinstance(heard, Relayed) else str(heard.key_expr)
        sender = Keys.id_of(key)
        if sender == self.id:
            return None
        try:
            m = decode(heard.payload if isinstance(heard, Relayed) else heard.payload.to_bytes(), State)
            if sender is None or m.id != sender or not key.startswith(self.keys.prefix + "/") or not key.endswith("/state"):
                raise MessageError("state id does not match its key")
        except MessageError:
            self._count_malformed(key)
            return None
        if m.wall is not None:
            self.state_latency.add((time.time() - m.wall) * 1000.0)
        return m

    def _on_alive(self, sample: zenoh.Sample) -> None:
        rid = Keys.id_of(str(sample.key_expr))
        if rid is None or rid == self.id:
            return
        if sample.kind == zenoh.SampleKind.DELETE:
            self.judge.deleted(rid)  # real time: gone once the link says it was not our own loss (_link_tick)
            log.info("agent %d: robot %d's liveliness token went away", self.id, rid)
            return
        self.judge.returned(rid)
        with self._cv:
            self._in.dead.discard(rid)

    # --- main loop -------------------------------------------------------------------
    def run(self) -> int:
        if self.cfg.record is not None or self.cfg.viz is not None:  # a RecorderError here: before any command
            from .view import start_view

            self.view = start_view(self.cfg)
        if self.cfg.record is not None:
            self.steplog = StepLogger(self.pipeline, self.cfg.lockstep, self.driver.name)
        if self.cfg.log_steps or self.cfg.step_log:
            self.steplog_fleet = StepLogger(self.pipeline, self.cfg.lockstep, self.driver.name, refs=True)
        if self.cfg.step_log:
            self._step_file = open(self.cfg.step_log, "ab", buffering=STEP_LOG_BUFFER)  # noqa: SIM115 - closed below
        try:
            return self._run()
        finally:
            if self.view is not None:
                self.view.stop()
            if self._step_file is not None:
                self._step_file.close()

    def _run(self) -> int:
        k = self.keys
        s = self.session
        block = zenoh.CongestionControl.BLOCK
        self._state_pub = s.declare_publisher(k.robot(self.id, "state"), congestion_control=block)
        self._diag_pub = s.declare_publisher(k.robot(self.id, "diag"), congestion_control=block)
        self._answer_pub = s.declare_publisher(k.robot(self.id, "answer"), congestion_control=block)
        if self.cfg.log_steps:
            self._step_pub = s.declare_publisher(k.robot(self.id, STEP_IO), congestion_control=block)
        subs = [
            s.declare_subscriber(k.robot(self.id, "fix"), self._on_fix),
            s.declare_subscriber(k.world("clock"), self._on_clock),
            s.declare_subscriber(k.world("status"), self._on_world_status),
            s.liveliness().declare_subscriber(k.all_alive, self._on_alive, history=True),
        ]
        if not self.cfg.lockstep:  # lock-step: the neighbours' states come in the world's clock (StateRelay)
            subs.append(s.declare_subscriber(k.all_robots("state"), self._on_state))
        if self.lidar is None:
            subs.append(s.declare_subscriber(k.robot(self.id, "scan"), self._on_scan))
        if self.virtual is not None:
            subs.append(s.declare_subscriber(k.robot(self.id, "virtual_scan"), self._on_virtual_scan))
        token = None
        try:
            self.ros_graph = open_ros_graph(self.robot, s, self._count_malformed)
            with self.driver, (self.lidar or contextlib.nullcontext()):
                token = s.liveliness().declare_token(k.alive(self.id))
                log.info("agent %d (%s, policy %s, driver %s) up on %s", self.id, self.role, self.pipeline.policy.name,
                         self.driver.name, self.cfg.connect)
                log.info("agent %d robot config: %s", self.id, self.robot)
                log.info("agent %d estimator config: %s; step config: %s", self.id, self.pipeline.ekf_config,
                         self.pipeline.cfg)
                try:
                    _freeze_startup_objects()
                    self._loop()
                finally:
                    self.driver.stop()  # zero velocity before anything else on the way out
                    self.pipeline.planner.close()
                    self._publish_diag("stopped")
        finally:
            if self.ros_graph is not None:
                self.ros_graph.close()
            if token is not None:
                token.undeclare()
            for sub in subs:
                sub.undeclare()
        return 0

    def _loop(self) -> None:
        gather = self._lockstep_inputs if self.cfg.lockstep else self._realtime_inputs
        steps = 0
        next_tick = time.monotonic()
        while not self.cfg.stop.is_set():
            if not self.cfg.lockstep:  # real time: the agent's own period on its monotonic clock
                delay = next_tick - time.monotonic()
                if delay > 0 and self.cfg.stop.wait(delay):
                    break
                next_tick = max(next_tick + self.dt, time.monotonic() - self.dt)  # late by > a period: skip ahead
            t_tick = time.perf_counter()  # real time: the tick; lock-step: reset once the barrier has let go
            inp = gather()
            if inp is None:
                continue
            if self.cfg.lockstep:
                t_tick = time.perf_counter()
            if self.ros_graph is not None and (goal := self.ros_graph.take_goal(self.pipeline)) is not None:
                inp = replace(inp, goal=goal)  # in the step's inputs: its log holds it
            self._send(inp, self.pipeline.step(inp))
            self.compute.add((time.perf_counter() - t_tick) * 1000.0)
            steps += 1
            if self.cfg.steps is not None and steps >= self.cfg.steps:
                break

    # --- inputs ----------------------------------------------------------------------
    def _lockstep_inputs(self) -> StepInputs | None:
        """Step k's inputs, once the barrier has them all; every time in them is the world's sim time."""
        with self._cv:
            got = self.barrier.wait_step(self.step, self._sensors_ready, lambda: len(self._in.odometry), self.cfg.stop,
                                         self._missing)
            if got is None:
                return None
            clock, n_device = got
            k = clock.step
            if not self.barrier.wait_neighbours(clock, self.step < 0, self.cfg.stop):
                return None
            # the driver's clock moves to step k only now that all of step k's device traffic is in (heartbeats go
            # before the odometry on each wire): whatever the wall clock did, the driver stamped it t_{k-1}
            if self.step < 0 and clock.t > self.sim_now:  # a restart: the driver opened at 0, the world is at t
                self.driver.clock_jumped(clock.t - self.sim_now)
            self.sim_now = max(self.sim_now, clock.t)
            odometry = self._take_odometry(k, clock.t, n_device)
            fixes = tuple((f.x, f.y, f.std) for f in self._in.fixes if f.step <= k)
            self._in.fixes = [f for f in self._in.fixes if f.step > k]
            # only states sent before this step are offered, in a fixed order (determinism)
            take = sorted((m for m in self._in.states if m.step < k), key=lambda m: (m.step, m.id, m.seq))
            self._in.states = [m for m in self._in.states if m.step >= k]
            scan, scan_t = self._in.scan, clock.t
            if self.lidar is not None:  # the robot's own lidar: when the newest scan came, to the step
                if self._in.lidar_n != self._lidar_taken[0]:
                    self._lidar_taken = (self._in.lidar_n, clock.t)
                scan_t = self._lidar_taken[1]
        # who is gone: the world's list of step k (every agent drops a robot at the same step)
        return StepInputs(step=k, t=clock.t, t_run=clock.t, now=clock.t, odometry=odometry, scan=scan, scan_t=scan_t,
                          fixes=fixes, states=tuple(take), dead=frozenset(clock.dead))

    def _sensors_ready(self, k: int) -> bool:
        """Lock-step: step k's scan, and a step-carrying driver's sample of k (with its gyro rate where the base
        has one), and the fix if one is due, are in (zenoh keeps order per key, not across keys)."""
        if self.lidar is not None:
            if not self._lidar_ready(k):
                return False
        elif self._in.scan is None or self._in.scan.step < k:
            return False
        if self.driver.answers_steps:
            q = self._in.odometry
            if not q or q[-1][0].step < k or (self.driver.has_imu and q[-1][0].wz_imu is None):
                return False
        if fix_due(self.robot, k, self.dt):
            return any(f.step == k for f in self._in.fixes)
        return True

    def _missing(self, k: int) -> str:
        """What step k still lacks, for the stall's error (caller holds the lock)."""
        q, scan = self._in.odometry, self._in.scan
        odo = "none" if not q else f"{q[-1][0].step}" + (" without its gyro rate" if q[-1][0].wz_imu is None else "")
        return (f"newest scan of step {None if scan is None else scan.step}, newest odometry of step {odo}, "
                f"a fix due: {fix_due(self.robot, k, self.dt)}")

    def _lidar_ready(self, k: int) -> bool:
        """Lock-step: step k's scans of the robot's own lidar are in, as many as the world's clock says its
        simulated sensor sent since our first step (caller holds the lock). Bounded by DEVICE_ODOM_WAIT_S: a
        scan lost on the wire is counted in ``lidar_late`` and written off, never a stall."""
        sent = self.barrier.clocks[k].device_scans.get(self.id)
        got = self._in.lidar_n
        if sent is None:
            return True  # no simulated sensor: a real one, at its own rate
        if self._lidar_sync is None:
            self._lidar_sync = (sent, got)  # our first step: what came before is history
            return True
        missing = (sent - self._lidar_sync[0]) - (got - self._lidar_sync[1])
        if missing <= 0:
            return True
        if self._lidar_wait is None or self._lidar_wait[0] != k:
            self._lidar_wait = (k, time.monotonic() + DEVICE_ODOM_WAIT_S)
        if time.monotonic() < self._lidar_wait[1]:
            return False
        self.lidar_late += 1
        log.warning("agent %d: step %d: %d lidar scan(s) missing after %.1f s; going on", self.id, k, missing,
                    DEVICE_ODOM_WAIT_S)
        self._lidar_sync = (self._lidar_sync[0], self._lidar_sync[1] - missing)
        return True

    def _take_odometry(self, k: int, t: float, n_device: int | None) -> tuple[OdomSample, ...]:
        """Lock-step (caller holds the lock): a step-carrying driver's samples up to step k at their own sim
        time; a device's newest ``n_device`` samples spread evenly over the step just ended (the newest at its
        end: a 100 Hz encoder's ten samples each predict over their own 10 ms), older ones dropped (strays)."""
        q = self._in.odometry
        if self.driver.answers_steps:
            items = [e for e in q if e[0].step <= k]
            rest = [e for e in q if e[0].step > k]
            times = [e[0].stamp for e in items]
        else:  # a device's samples of the step just ended: spread over it at their rate, the newest at t
            items = list(q)[len(q) - min(n_device or 0, len(q)):]
            rest = []
            n = len(items)
            times = [t - self.dt * (n - 1 - i) / n for i in range(n)]
        q.clear()
        q.extend(rest)
        return tuple(_sample(odo, fix, ts) for (odo, fix, _), ts in zip(items, times))

    def _link_tick(self, now: float) -> str | None:
        """Real time, each tick: our link to the router(s) (``"no-network"`` while it is down: the robot holds),
        and the peers whose tokens went away while it was up (gone)."""
        change = self.link.poll()
        if change == "lost":
            log.warning("agent %d: t=%.1f s: lost its router(s): holding (zero velocity; peers kept, no failover) "
                        "until the link is back", self.id, now)
        elif change == "back":
            o = self.link.outages[-1]
            log.warning("agent %d: t=%.1f s: router link back after %.1f s: going on", self.id, now, o.end - o.start)
        gone = self.judge.confirmed()
        if gone:
            log.info("agent %d: robots %s left (liveliness lost while our link was up)", self.id, gone)
            with self._cv:
                self._in.dead.update(gone)
        return None if self.link.up else "no-network"

    def _realtime_inputs(self) -> StepInputs | None:
        """Real time: what arrived by this tick. Nothing before the first odometry sample and the first scan."""
        now = self._now()
        held = self._link_tick(now)
        if held is not None:
            self._hold("no router")
        with self._cv:
            scan = self._current_scan(now)
            if scan is not None and self.virtual is not None:  # the virtual robots and obstacles, where fresh
                scan = self.virtual.merge(scan, now)
            if scan is None or (not self._in.odometry and self.step < 0):
                self._hold("no odometry and scan yet")
                return None
            odometry = tuple(_sample(odo, fix, t) for odo, fix, t in self._in.odometry)
            self._in.odometry.clear()
            fixes = tuple((f.x, f.y, f.std) for f in self._in.fixes)
            self._in.fixes = []
            states, self._in.states = tuple(self._in.states), []
            wc = self._in.world_clock
            t_run = wc[0] + (now - wc[1]) if wc is not None else now
            dead, scan_t = frozenset(self._in.dead), self._in.scan_t
            if held is None and self._await_world and wc is None:  # the simulated robots have not started yet
                held = "no-world"
        return StepInputs(step=self.step + 1, t=now, t_run=t_run, now=time.time(), odometry=odometry, scan=scan,
                          scan_t=scan_t, fixes=fixes, states=states, dead=dead, held=held)

    def _current_scan(self, now: float) -> Scan | None:
        """The newest scan: the world's, or the robot's own where its driver reads one (a Jackal's ``LaserScan``:
        swap the driver, nothing else), or its own lidar source's. Caller holds the lock."""
        if self.lidar is not None or not self.driver.provides_scan:
            return self._in.scan
        data = self.driver.read_scan()
        if data is None:
            return None
        held = self._in.driver_scan
        if held is None or held[0] is not data:
            n = held[1].step + 1 if held is not None else 0
            self._in.driver_scan = (data, scan_from_driver(self.robot, data, n))
            self._in.scan_t = now
            self.scans_from_driver += 1
        return self._in.driver_scan[1]

    def _hold(self, why: str) -> None:
        if self.driver.last_sent != (0.0, 0.0):
            log.warning("agent %d: %s: zero velocity", self.id, why)
            self.driver.stop()

    # --- output ----------------------------------------------------------------------
    def _send(self, inp: StepInputs, out: StepOutput) -> None:
        first, k = self.step < 0, inp.step
        self.step = k
        if self.driver.fault and not self.fault:
            self.fault = f"{self.driver.name} driver: {self.driver.fault}"
            log.error("agent %d: %s: the robot is stopped (zero velocity) from t=%.1f s", self.id, self.fault, inp.t_run)
            self._publish_diag("fault")
        if out.stale != self._stale:
            if out.stale is not None and not first:  # a robot that has not moved yet is not stopped
                self.sensor_stale += 1
                log.warning("agent %d: t=%.1f s: %s stale: zero velocity", self.id, inp.t_run, out.stale)
            self._stale = out.stale
        p = out.pose
        self.seq += 1
        st = State(id=self.id, role=self.role, seq=self.seq, stamp=self._stamp(), x=p.x, y=p.y, yaw=p.yaw, v=p.v, w=p.w,
                   step=k, situation=out.situation, wall=time.time(), cov_trace=out.cov_trace, d_goal=out.d_goal)
        self._state_pub.put(encode(st))
        self.sent += 1
        v, w = out.v, out.w
        if self.virtual is not None:  # the virtual side lost: slower (virtual.py)
            v, w = self.virtual.hold(v, w, self._now())
        self.driver.command(v, w, step=k)
        if self.cfg.lockstep and not self.driver.answers_steps:  # the command went over the device's wire
            self._answer_pub.put(encode(Answer(id=self.id, step=k, stamp=self._stamp(), wire=self.driver.wire_sent,
                                               sync=first)))
        # after the answer: the world's step waits for nothing of it
        if self.steplog_fleet is not None:
            payload = self.steplog_fleet.record(inp, out, self.driver.last_sent)
            if self._step_file is not None:
                self._step_file.write(payload + b"\n")
            if self._step_pub is not None:
                self._step_pub.put(payload)
        if self.view is not None:
            if self.steplog is not None:
                self.view.on_step_io(self.steplog.record(inp, out, self.driver.last_sent), inp.now)
            self.view.on_step(self.pipeline, inp, out, self.driver.last_sent)
        self.hist.add((time.perf_counter() - self._in.sensor_perf) * 1000.0)
        if self.ros_graph is not None:  # hands the step over to its publisher thread; a goal for the next step
            self.ros_graph.step(inp.t, self._stamp(), self.pipeline)
        if k % 10 == 0:
            self._publish_diag("running")

    def _publish_diag(self, state: str) -> None:
        pl = self.pipeline
        c, pc = pl.radio.counters, pl.counters
        with self._cv:
            malformed = dict(self.malformed)
            wc = self._in.world_clock
        off = wc[0] - wc[1] if wc is not None else 0.0  # our clock -> run time (the world's, where we hear one)
        d = Diag(id=self.id, stamp=self._stamp(), step=self.step, state=state, sent=self.sent, received=c.received,
                 delivered=c.delivered, dropped_loss=c.dropped_loss, dropped_range=c.dropped_range,
                 malformed=sum(malformed.values()), malformed_by_key=malformed, loop_hist=self.hist.as_dict(),
                 compute_hist=self.compute.as_dict(), state_latency_hist=self.state_latency.as_dict(),
                 situations={k: v for k, v in pl.decision.counts.items() if v}, fixes_used=pc.fixes_used,
                 fixes_rejected=pl.estimator.rejected_fixes, inputs_rejected=pl.estimator.rejected_nan,
                 sensor_stale=self.sensor_stale, fault=self.fault, noticed=dict(pc.noticed), led_since=pl.led_since,
                 rejected_states=pc.rejected_states, neighbour_waits_timed_out=self.barrier.neighbour_timeouts,
                 device_odom_late=self.barrier.device_late, device_odom_strays=self.barrier.strays,
                 odom_stale=pc.odom_stale, lidar_stale=pc.lidar_stale, scans_from_driver=self.scans_from_driver,
                 shield_masked=getattr(pl.policy, "masked", None), guard_caps=pl.guard.capped,
                 guard_slides=pl.guard.slides, guard_brakes=pl.guard.brakes, links=pl.radio.links(), stuck=pl.decision.livelock(),
                 planner=pl.planner.stats() if pl.planner.tickets else None,
                 led=[list(iv) for iv in pl.drove_led], held_steps=pl.held_steps, tokens_kept=self.judge.discarded,
                 link_outages=[[o.start + off, None if o.end is None else o.end + off] for o in self.link.outages],
                 virtual=None if self.virtual is None else self.virtual.counters())
        self._diag_pub.put(encode(d))
        if self.view is not None:
            self.view.on_diag(d)


def _freeze_startup_objects() -> None:
    """Everything built at start-up (modules, the scenario, the policy, the driver) out of the collector's way:
    a collection then walks only what the loop allocates (``gc`` was ~15 % of an agent's native samples at 4
    robots, docs/profile.md), and a forked agent keeps those pages shared."""
    gc.collect()
    gc.freeze()


def _sample(odo, fix, t: float) -> OdomSample:
    return OdomSample(v=odo.v, w=odo.w, t=t, wz_imu=odo.wz_imu, pose=odo.pose, fix=fix)
