"""A simulated Clearpath Jackal J100 as the world hosts it: what zenoh-bridge-ros2dds shows of a real one.

On the world's Zenoh session, under the robot's namespace ``ns`` (default
``jackal/<fleet>/robot<id>``: unique per fleet, so parallel fleets never meet), with the
payloads of the ROS 2 messages in CDR (``stack.drivers.ros2cdr``, the driver's own
encoders and decoders):

- subscribes ``<ns>/cmd_vel`` (``geometry_msgs/Twist``); the newest command is the target;
- publishes ``<ns>/platform/odom/filtered`` (``nav_msgs/Odometry``, odom -> base_link);
- publishes ``<ns>/sensors/lidar2d_0/scan`` (``sensor_msgs/LaserScan``) when the world calls
  ``publish_scan`` with its lidar.

The controller is the Jackal's ``diff_drive_controller`` as ``jackal_control``'s
``control.yaml`` configures it: 50 Hz, speed limits 2.0 m/s and 4.0 rad/s (the driver
settings' ``v_max``/``w_max``, which default to those), acceleration
limits 20 m/s^2 and 25 rad/s^2 (the body speeds ramp toward the target at those rates, one
step per 20 ms tick), and the J100's ``cmd_vel`` timeout of 0.5 s: a target older than that
(device time) becomes zero. Velocity limits act on the body speeds, as the controller's
speed limiter does, so wheel separation and radius do not enter.

Odometry, ideal (``device: {ideal: true}``, for comparisons): ``report`` publishes one message per world step at the end of the step (lock-step),
stamped with the device time; before lock-step (and all along in real time) a thread
publishes at 50 Hz from the newest body the world reported, stamped with the wall-clock
device time, so a driver can open and see odometry. The pose is the body's pose in the
world frame (not a real Jackal's odom frame, which starts at 0, 0, 0 where it boots): the
agent's estimator then starts at the right pose, as it does with the ``sim`` driver's
odometry. The twist is the body's (v, w) as the world moved it, with the robot's
``odom_noise`` (v_std, w_std) added on the step's report (seeded by the scenario's seed).
Topic names come from the scenario's ``jackal`` driver settings, so driver and device agree.

Hardware-like (the default, ``JackalDeviceConfig(ideal=False)``, the robot's ``device:`` settings): odometry
at ``odom_rate_hz`` (50 Hz, robot_localization's rate) in the robot's odom frame, which is
(0, 0, 0) where it booted (its start pose; ``odom_frame: site`` keeps the world frame), its
pose dead-reckoned from the twist it reports (so it drifts with ``odom_noise``); the lidar at
``lidar_rate_hz`` with its own beam layout, no return as +inf (REP 117); every sample at its
own time (lock-step: the samples that fall in a world step go out when the step ends, the
body where it was then, on the arc the world moved it), stamped by the robot's own clock
(``clock_offset_s`` ahead of the world's), with ``jitter_s`` and ``drop_prob``. A scan taken
inside a step is cast by ``ray_caster`` at the pose of its time when the world gives one,
else it re-reads the world's newest scan (at the step's start).

``fail()`` (the world's ``--device-fault``) stops the odometry, as when the robot's EKF
dies: the driver's odometry timeout then faults it and it sends zero.

Malformed commands (not CDR, not a Twist, non-finite) are counted in ``counters``
(``cmd_not_cdr``, ``cmd_undecodable``, ``cmd_bad_value``) and ignored.

With the robot's ``jackal: {transport: rmw_zenoh}`` (the driver's settings, read here so both ends
agree) the Jackal is a robot running ``rmw_zenoh_cpp`` instead: its node ``<ns>/jackal_sim`` (``ns``
a ROS namespace: the fleet name's characters other than letters, digits and ``_`` become ``_``)
holds rmw_zenoh's liveliness tokens for itself, its odometry and scan publishers (scans with sensor
QoS) and its ``cmd_vel`` subscription; its samples carry rmw_zenoh's attachment and go on rmw_zenoh's
keys (``stack.drivers.rmw_zenoh``); and, as rmw_zenoh_cpp does, it drops the ``cmd_vel`` samples
without a valid attachment or of another type or type hash, counted as ``cmd_no_attachment``,
``cmd_bad_attachment``, ``cmd_type_mismatch``, ``cmd_hash_mismatch`` (``cmd_lost``: gaps in a
publisher's sequence numbers). Everything else, the hardware-like settings included, is the same on
both transports.
"""

from __future__ import annotations

import logging
import math
import re
import threading
from collections import deque
from dataclasses import dataclass, replace
from typing import Any, Callable, Sequence

import numpy as np
import zenoh

from ..drivers.jackal import JackalConfig
from ..drivers.rmw_zenoh import DEFAULT_QOS, SENSOR_QOS, RmwZenohNode
from ..drivers.ros2cdr import LASER_SCAN, ODOMETRY, TWIST, CdrError, decode_twist, encode_laserscan, encode_odometry
from .device_streams import Stream, arc, relative_pose
from .devices import SIM_OPEN_TIMEOUT_S, Body, DeviceConfig, DeviceError, HostedDevice, check_choice, check_number

log = logging.getLogger(__name__)

CONTROL_RATE = 50.0  # [Hz] the diff drive controller's update rate
ODOM_RATE = 50.0  # [Hz] robot_localization's EKF frequency on the Jackal
ACCEL_MAX = 20.0  # [m/s^2] control.yaml linear.x.max_acceleration
ALPHA_MAX = 25.0  # [rad/s^2] control.yaml angular.z.max_acceleration
CMD_TIMEOUT = 0.5  # [s] the J100's cmd_vel timeout (the controller stops)
LIDAR_RATE = 25.0  # [Hz] a SICK LMS111 (the Jackal's stock 2D lidar) at its slower setting
NODE_NAME = "jackal_sim"  # the simulated robot's ROS 2 node (rmw_zenoh transport)


@dataclass(frozen=True)
class JackalDeviceConfig(DeviceConfig):
    """How the simulated Jackal behaves (scenario: the robot's ``device:``); used only with ``ideal: false`` (the default)."""

    odom_rate_hz: float = ODOM_RATE
    """[Hz] rate of ``platform/odom/filtered`` (robot_localization's EKF on a Jackal: 50 Hz)."""
    odom_frame: str = "boot"
    """``boot``: odometry in the robot's odom frame, (0, 0, 0) where it booted (the hardware);
    ``site``: in the world (site) frame."""
    lidar_rate_hz: float = LIDAR_RATE
    """[Hz] scan rate of the 2D lidar (SICK LMS111: 25/50, Hokuyo UST-10: 40, RPLidar A1: 5-15); default 25 Hz,
    the slowest of the Jackal's stock lidars (an LMS111 at 25 Hz), not the control rate."""
    lidar_beams: int | None = None
    """Beams per scan; None: the scenario's lidar."""
    lidar_fov_deg: float | None = None
    """[deg] field of view, centred ahead; None: the scenario's lidar."""
    no_return: str = "inf"
    """A beam without a return reads ``inf`` (REP 117) or ``range_max`` (older drivers)."""
    clock_offset_s: float = 0.0
    """[s] how far the robot's clock (its header stamps) is ahead of the world's (negative: behind)."""
    jitter_s: float = 0.0
    """[s] standard deviation of each sample's time about its nominal tick (clipped to 0.45 of a period)."""
    drop_prob: float = 0.0
    """Probability that a sample (odometry or scan) is lost on the way."""

    def __post_init__(self):
        super().__post_init__()
        check_number("odom_rate_hz", self.odom_rate_hz, high=1000.0, low_open=True)
        check_number("lidar_rate_hz", self.lidar_rate_hz, high=1000.0, low_open=True)
        check_choice("odom_frame", self.odom_frame, ("boot", "site"))
        check_choice("no_return", self.no_return, ("inf", "range_max"))
        if self.lidar_beams is not None and (isinstance(self.lidar_beams, bool) or not isinstance(self.lidar_beams, int)
                                             or not 1 <= self.lidar_beams <= 10_000):
            raise ValueError(f"lidar_beams must be an integer 1..10000, not {self.lidar_beams!r}")
        if self.lidar_fov_deg is not None:
            check_number("lidar_fov_deg", self.lidar_fov_deg, high=360.0, low_open=True)
        check_number("clock_offset_s", self.clock_offset_s, low=None)
        check_number("jitter_s", self.jitter_s)
        check_number("drop_prob", self.drop_prob, high=0.99)


def _toward(value: float, target: float, step: float) -> float:
    return target if abs(target - value) <= step else value + math.copysign(step, target - value)


class _HardwareTelemetry:
    """The hardware-like Jackal's odometry and scans: own rates, odom frame, own clock, jitter, losses.

    Lock-step: ``report`` sends the odometry samples of the step just ended and the scans taken in it
    (before its end), ``world_scan`` those taken at the step's start. Real time: ``tick`` sends what is due
    on the wall clock from the newest body and world scan. Guarded by ``lock`` (real time: two threads).
    """

    def __init__(self, dev: "JackalDevice", cfg: JackalDeviceConfig):
        self.dev, self.cfg = dev, cfg
        self.lock = threading.Lock()
        self._rng = np.random.default_rng([dev.seed, dev.robot_id, 12])
        self.odom, self.scan = self._streams()
        robot = dev.robot
        self.origin = tuple(robot.pose) if cfg.odom_frame == "boot" else (0.0, 0.0, 0.0)
        lid = robot.lidar
        beams = cfg.lidar_beams if cfg.lidar_beams is not None else lid.beams
        fov = math.radians(cfg.lidar_fov_deg) if cfg.lidar_fov_deg is not None else lid.fov
        self.angles = np.zeros(1) if beams == 1 else np.linspace(-fov / 2, fov / 2, beams)
        self.increment = fov / (beams - 1) if beams > 1 else 0.0
        self.range_max = float(lid.range)
        self.pose: tuple[float, float, float] | None = None  # the odometry's own (dead-reckoned) pose
        self.pose_t = 0.0  # sim time of that pose
        self.twist: tuple[float, float] | None = None  # the newest (noisy) twist measured in this step
        self.prev: tuple[Body, float] | None = None  # body and time of the previous report
        self.world: tuple[float, float, np.ndarray] | None = None  # newest world scan: angle_min, increment, ranges
        x, y, yaw = robot.pose
        self.realtime_body = (Body(x, y, yaw, 0.0, 0.0), 0.0)  # newest body and the wall time it came

    def reseed(self) -> None:
        """Jitter and losses from the seed again (lock-step starts)."""
        with self.lock:
            self._rng = np.random.default_rng([self.dev.seed, self.dev.robot_id, 12])
            self.odom.rng = self.scan.rng = self._rng

    def _streams(self) -> tuple[Stream, Stream]:
        c = self.cfg
        return (Stream(c.odom_rate_hz, jitter_s=c.jitter_s, drop_prob=c.drop_prob, rng=self._rng),
                Stream(c.lidar_rate_hz, jitter_s=c.jitter_s, drop_prob=c.drop_prob, rng=self._rng))

    # --- lock-step ----------------------------------------------------------------------
    def report(self, t: float, body: Body) -> None:
        with self.lock:
            if self.prev is None:  # the first lock-step report: the streams start here
                self.odom.restart(t)
                self.scan.restart(t)
                self.pose, self.pose_t = relative_pose(self.origin, (body.x, body.y, body.yaw)), t
                self.prev = (body, t)
            prev, t0 = self.prev
            for ts, kept in self.scan.due(t, inclusive=False):
                self._send_scan(ts, kept, self._pose_between(prev, t0, body, ts))
            self.twist = None
            for ts, kept in self.odom.due(t):
                self._send_odom(ts, kept, body)
            v, w = self.twist or (body.v, body.w)  # the rest of the step at its speeds: the next one starts here
            self.pose, self.pose_t = arc(self.pose, v, w, t - self.pose_t), t
            self.prev = (body, t)

    def world_scan(self, t: float, angle_min: float, increment: float, ranges) -> None:
        with self.lock:
            self.world = (angle_min, increment, np.asarray(ranges, float))
            if self.prev is None or not self.dev.in_lockstep:
                return
            body = self.prev[0]
            for ts, kept in self.scan.due(t):
                self._send_scan(ts, kept, (body.x, body.y, body.yaw))

    @staticmethod
    def _pose_between(prev: Body, t0: float, body: Body, t: float) -> tuple[float, float, float]:
        """Where the body was at ``t`` in (t0, t1]: on the arc the world moved it with (v, w) of the step."""
        return arc((prev.x, prev.y, prev.yaw), body.v, body.w, t - t0)

    def _send_odom(self, t: float, kept: bool, body: Body) -> None:
        """Dead-reckon the odometry's pose to ``t`` with the (noisy) twist, then send it stamped on the robot's clock."""
        v, w = self.twist = self.dev.noisy_twist(body.v, body.w)
        self.pose = arc(self.pose, v, w, t - self.pose_t)
        self.pose_t = t
        if kept:
            self.dev.publish_odom(self.dev.host_clock(t, self.cfg.clock_offset_s), *self.pose, v, w)

    def _send_scan(self, t: float, kept: bool, pose: tuple[float, float, float], cast: bool = True) -> None:
        """One scan at ``t`` from ``pose``: cast by the world there (``cast``, lock-step only: the world's
        thread), else the world's newest scan."""
        if not kept:
            return
        caster = self.dev.ray_caster if cast else None
        if caster is not None:
            ranges = np.asarray(caster(*pose, self.angles), float)
        elif self.world is not None:
            ranges = self._resample(*self.world)
        else:
            return
        if self.cfg.no_return == "inf":
            ranges = np.where(ranges >= self.range_max - 1e-6, np.inf, ranges)
        self.dev.publish_laserscan(self.dev.host_clock(t, self.cfg.clock_offset_s), float(self.angles[0]),
                                   self.increment, self.range_max, ranges, 1.0 / self.cfg.lidar_rate_hz)

    def _resample(self, angle_min: float, increment: float, ranges: np.ndarray) -> np.ndarray:
        """The world's scan read at our beam angles (nearest beam); outside its field of view: no return."""
        if ranges.size == self.angles.size and abs(angle_min - self.angles[0]) < 1e-9:
            return ranges
        if ranges.size == 1 or increment == 0:
            return np.full(self.angles.size, float(ranges[0]))
        idx = np.rint((self.angles - angle_min) / increment).astype(int)
        inside = (idx >= 0) & (idx < ranges.size)
        return np.where(inside, ranges[np.clip(idx, 0, ranges.size - 1)], self.range_max)

    # --- real time ----------------------------------------------------------------------
    def tick(self, now: float) -> float:
        """Send what is due by wall time ``now`` (device time); returns the time of the next sample."""
        with self.lock:
            body, at = self.realtime_body
            pose = arc((body.x, body.y, body.yaw), body.v, body.w, max(0.0, now - at))
            for _, kept in self.odom.due(now):
                v, w = self.dev.noisy_twist(body.v, body.w)
                if kept:
                    self.dev.publish_odom(self.dev.host_clock(None, self.cfg.clock_offset_s),
                                          *relative_pose(self.origin, pose), v, w)
            for ts, kept in self.scan.due(now):
                self._send_scan(ts, kept, pose, cast=False)
            return min(self.odom.next_time, self.scan.next_time)


class JackalDevice(HostedDevice):
    """One simulated Jackal behind one robot's ``jackal`` driver, on the world's Zenoh session.

    ``namespace``: the robot's key prefix (default ``jackal/<fleet>/robot<id>`` from ``keys``,
    ``robot<id>`` without); it overrides the scenario's. ``on_malformed`` is told
    ``jackal/<counter>`` for each malformed command. The rest (``run_dir``, ``session``,
    ``keys``, ``seed``) are HostedDevice's; ``session`` is required.
    """

    kind = "jackal"
    config_class = JackalDeviceConfig

    def __init__(self, robot, *, namespace: str | None = None, on_malformed: Callable[[str], None] | None = None,
                 **kw):
        super().__init__(robot, **kw)
        if self.session is None:
            raise DeviceError(f"robot {robot.id}: the jackal device needs the world's zenoh session")
        if namespace is None:
            namespace = self._default_namespace(robot)
        cfg = self.driver_config(JackalConfig, namespace=namespace)  # the topics as the driver has them, our namespace
        self._cfg = cfg
        self._open_timeout = cfg.open_timeout
        self.namespace = namespace
        self.cmd_key = cfg.topic_key(robot.id, cfg.cmd_topic, TWIST)
        self.odom_key = cfg.topic_key(robot.id, cfg.odom_topic, ODOMETRY)
        self.scan_key = cfg.topic_key(robot.id, cfg.scan_topic, LASER_SCAN)
        self.node: RmwZenohNode | None = None  # rmw_zenoh: the robot's node while started
        self.v_max, self.w_max = cfg.v_max, cfg.w_max  # control.yaml max_velocity: 2.0 m/s, 4.0 rad/s
        self._on_malformed = on_malformed or (lambda key: None)
        self._odom_noise = robot.odom_noise  # (v_std, w_std) on the reported twist, as the sim driver's odometry
        self._rng = np.random.default_rng([self.seed, robot.id, 11])
        self.counters: dict[str, int] = {}
        self.odom_stopped = False  # fail(): no more odometry
        self.target = (0.0, 0.0)  # (v, w) the newest command, clamped to the controller's limits
        self.target_time: float | None = None  # device time it came; None: none, or timed out
        self.velocity = (0.0, 0.0)  # (v, w) the controller's output after the acceleration limits
        x, y, yaw = robot.pose
        self.body = Body(x, y, yaw, 0.0, 0.0)  # the newest body the world reported
        self._pending: deque[tuple[bytes, float | None]] = deque(maxlen=256)  # (payload, wall arrival or None)
        self._lock = threading.Lock()  # guards _pending
        self._t: float | None = None  # sim time the controller has reached
        self._declared: list = []  # the subscriber and publishers (bridge) or the node (rmw_zenoh)
        self._pubs: dict[str, Any] = {}  # key -> a zenoh Publisher or an RmwPublisher: put(payload) either way
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        cfg = self.device_config
        self.hardware = None if cfg.ideal else _HardwareTelemetry(self, cfg)

    # --- lifecycle ----------------------------------------------------------------------
    def _default_namespace(self, robot) -> str:
        """``jackal/<fleet>/robot<id>`` (``robot<id>`` without keys); on rmw_zenoh a ROS namespace."""
        if self.keys is None:
            return f"robot{robot.id}"
        fleet = self.keys.fleet
        if dict(robot.driver_params.get(self.kind, {})).get("transport") == "rmw_zenoh":
            fleet = re.sub(r"[^A-Za-z0-9_]", "_", fleet)
            fleet = fleet if re.match(r"[A-Za-z_]", fleet) else f"_{fleet}"
        return f"jackal/{fleet}/robot{robot.id}"

    def start(self) -> None:
        if self._cfg.transport == "rmw_zenoh":
            self._start_node()
        else:
            self._pubs = {k: self.session.declare_publisher(k, encoding=zenoh.Encoding.APPLICATION_CDR)
                          for k in (self.odom_key, self.scan_key)}
            self._declared = [*self._pubs.values(), self.session.declare_subscriber(
                self.cmd_key, lambda sample: self._queue_cmd(sample.payload.to_bytes()))]
        self._halt.clear()
        self._thread = threading.Thread(target=self._run_realtime, name=f"jackal-device-{self.robot_id}", daemon=True)
        self._thread.start()

    def _start_node(self) -> None:
        """rmw_zenoh: the robot's node, its publishers (with attachments) and its checked cmd_vel subscription."""
        cfg = self._cfg
        self.node = node = RmwZenohNode(self.session, cfg.node_config(self.robot_id, NODE_NAME),
                                        on_malformed=self._rmw_malformed)
        self._declared = [node]
        self._pubs = {self.odom_key: node.publisher(cfg.odom_topic, ODOMETRY, DEFAULT_QOS),
                      self.scan_key: node.publisher(cfg.scan_topic, LASER_SCAN, SENSOR_QOS)}
        node.subscribe(cfg.cmd_topic, TWIST, lambda payload, attachment: self._queue_cmd(payload))

    def _rmw_malformed(self, kind: str) -> None:
        """The node dropped a cmd_vel sample, as rmw_zenoh_cpp does (or saw a gap: ``lost``, not malformed)."""
        if kind == "lost":
            self._count("cmd_lost")  # gaps; node.counters["lost"]: samples
        else:
            self._malformed(f"cmd_{kind}")

    def driver_params(self) -> dict[str, Any]:
        return {"namespace": self.namespace, "open_timeout": max(self._open_timeout, SIM_OPEN_TIMEOUT_S)}

    def lockstep(self, t_sim: float) -> None:
        """Sim time from here; the random streams start again from the seed, so what the wall-clock phase
        before drew (how many samples it sent depends on the machine) never shows in a lock-step run."""
        super().lockstep(t_sim)
        self._rng = np.random.default_rng([self.seed, self.robot_id, 11])
        if self.hardware is not None:
            self.hardware.reseed()

    def _send_status(self, t_sim: float) -> None:
        """Odometry of the body standing where it is (a driver opening waits for the first one)."""
        if self.hardware is None:
            self._publish_odom(self.device_time(t_sim), replace(self.body, v=0.0, w=0.0))
        elif self.hardware.pose is not None:
            self.publish_odom(self.host_clock(t_sim, self.hardware.cfg.clock_offset_s), *self.hardware.pose, 0.0, 0.0)

    def _restart_timers(self, t_dev: float) -> None:
        """The cmd_vel timeout counts from the handover (a target it holds is as old as that)."""
        if self.target_time is not None:
            self.target_time = t_dev

    def _stop_realtime(self) -> None:
        self._halt.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None

    def close(self) -> None:
        self._stop_realtime()
        self._pubs = {}
        self.node = None
        while self._declared:
            self._declared.pop().undeclare()

    def _run_realtime(self) -> None:
        wait = 1.0 / ODOM_RATE
        while not self._halt.wait(wait):
            try:
                if self.hardware is None:
                    self._publish_odom(self.wall_time(), self.body)
                else:
                    wait = max(0.0, self.hardware.tick(self.wall_time()) - self.wall_time())
            except zenoh.ZError as e:  # the world's session is gone: so is the robot
                log.warning("jackal device %s: odometry on %s stopped: %s", self.robot_id, self.odom_key, e)
                return

    # --- commands in --------------------------------------------------------------------
    def _queue_cmd(self, payload: bytes) -> None:
        """Zenoh thread (either transport): queue the payload; on the wall clock the arrival is its device time."""
        arrived = None if self.in_lockstep else self.wall_time()
        with self._lock:
            if len(self._pending) == self._pending.maxlen:
                self.wire_received += 1  # the oldest is dropped unread: handled, as far as the count goes
            self._pending.append((payload, arrived))

    def take_commands(self, t_sim: float) -> None:
        now = self.device_time(t_sim)
        if self._t is None:
            self._t = t_sim
        with self._lock:
            items = list(self._pending)
            self._pending.clear()
            self.wire_received += len(items)
        for data, arrived in items:
            try:
                v, w = decode_twist(data)
            except CdrError as e:
                self._malformed(f"cmd_{e.kind}")
                continue
            self.target = (max(-self.v_max, min(self.v_max, v)), max(-self.w_max, min(self.w_max, w)))
            self.target_time = now if arrived is None else arrived
            self._count("cmd")

    # --- the controller -----------------------------------------------------------------
    def motion(self, t_sim_next: float) -> tuple[float, float]:
        """Controller ticks at 50 Hz over the step; the mean body speeds over it."""
        t0 = t_sim_next if self._t is None else self._t
        dt = t_sim_next - t0
        if dt <= 0:
            return self.velocity
        n = max(1, math.ceil(dt * CONTROL_RATE - 1e-9))
        h = dt / n
        v, w = self.velocity
        sum_v = sum_w = 0.0
        for i in range(n):
            if self.target_time is not None and self.device_time(t0 + i * h) - self.target_time > CMD_TIMEOUT + 1e-9:
                self.target, self.target_time = (0.0, 0.0), None
                self._count("cmd_timeout")
            v = _toward(v, self.target[0], ACCEL_MAX * h)
            w = _toward(w, self.target[1], ALPHA_MAX * h)
            sum_v, sum_w = sum_v + v, sum_w + w
        self.velocity = (v, w)
        self._t = t_sim_next
        return sum_v / n, sum_w / n

    # --- telemetry out ------------------------------------------------------------------
    def report(self, t_sim_next: float, body: Body) -> None:
        if self.hardware is not None:
            if self.in_lockstep:
                self.hardware.report(t_sim_next, body)
            else:
                with self.hardware.lock:
                    self.hardware.realtime_body = (body, self.wall_time())
            self.body = body
            return
        v, w = self.noisy_twist(body.v, body.w)
        body = replace(body, v=v, w=w)
        self.body = body
        if self.in_lockstep:  # one odometry per step; on the wall clock the thread sends them at 50 Hz
            self._publish_odom(self.device_time(t_sim_next), body)

    def noisy_twist(self, v: float, w: float) -> tuple[float, float]:
        """The body's (v, w) with the robot's ``odom_noise`` (seeded)."""
        v_std, w_std = self._odom_noise
        if v_std or w_std:
            nv, nw = self._rng.normal(0.0, 1.0, 2) * (v_std, w_std)
            return v + float(nv), w + float(nw)
        return v, w

    def publish_scan(self, t_sim: float, angle_min: float, angle_increment: float, range_max: float,
                     ranges: Sequence[float]) -> None:
        """The world's lidar scan at ``t_sim`` as the Jackal's ``sensor_msgs/LaserScan`` (hardware-like: the
        newest world scan, for the scans the lidar takes at its own rate)."""
        if self.hardware is not None:
            self.hardware.world_scan(t_sim, angle_min, angle_increment, ranges)
            return
        self.publish_laserscan(self.device_time(t_sim), angle_min, angle_increment, range_max, ranges)

    def publish_laserscan(self, stamp: float, angle_min: float, angle_increment: float, range_max: float,
                          ranges: Sequence[float], scan_time: float = 0.0) -> None:
        pub = self._pubs.get(self.scan_key)
        if pub is not None:
            pub.put(encode_laserscan(stamp, angle_min, angle_increment, range_max, ranges, scan_time=scan_time))
            self._count("scan")

    def fail(self) -> str:
        self.odom_stopped = True
        return "the Jackal's filtered odometry stopped (its EKF died); cmd_vel still reaches the controller"

    def _publish_odom(self, stamp: float, body: Body) -> None:
        self.publish_odom(stamp, body.x, body.y, body.yaw, body.v, body.w)

    def publish_odom(self, stamp: float, x: float, y: float, yaw: float, v: float, w: float) -> None:
        pub = self._pubs.get(self.odom_key)
        if pub is not None and not self.odom_stopped:
            pub.put(encode_odometry(stamp, x, y, yaw, v, w))
            self._count("odom")
            self.odom_sent += 1

    # --- helpers ------------------------------------------------------------------------
    def _count(self, key: str) -> None:
        self.counters[key] = self.counters.get(key, 0) + 1

    def _malformed(self, kind: str) -> None:
        self._count(kind)
        self._on_malformed(f"jackal/{kind}")


__all__ = ["JackalDevice", "JackalDeviceConfig"]
