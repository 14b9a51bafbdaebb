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

Odometry: ``report`` publishes one message per world step at the end of the step (lock-step),
stamped with the device time; before lock-step (and all along in real time) a thread
publishes at 50 Hz from the newest body the world reported, stamped with the wall-clock
device time, so a driver can open and see odometry. The pose is the body's pose in the
world frame (not a real Jackal's odom frame, which starts at 0, 0, 0 where it boots): the
agent's estimator then starts at the right pose, as it does with the ``sim`` driver's
odometry. The twist is the body's (v, w) as the world moved it, with the robot's
``odom_noise`` (v_std, w_std) added on the step's report (seeded by the scenario's seed).
Topic names come from the scenario's ``jackal`` driver settings, so driver and device agree.

``fail()`` (the world's ``--device-fault``) stops the odometry, as when the robot's EKF
dies: the driver's odometry timeout then faults it and it sends zero.

Malformed commands (not CDR, not a Twist, non-finite) are counted in ``counters``
(``cmd_not_cdr``, ``cmd_undecodable``, ``cmd_bad_value``) and ignored.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from dataclasses import replace
from typing import Any, Callable, Sequence

import numpy as np
import zenoh

from ..drivers.jackal import JackalConfig
from ..drivers.ros2cdr import CdrError, decode_twist, encode_laserscan, encode_odometry
from .devices import SIM_OPEN_TIMEOUT_S, Body, DeviceError, HostedDevice

log = logging.getLogger(__name__)

CONTROL_RATE = 50.0  # [Hz] the diff drive controller's update rate
ODOM_RATE = 50.0  # [Hz] robot_localization's EKF frequency on the Jackal
ACCEL_MAX = 20.0  # [m/s^2] control.yaml linear.x.max_acceleration
ALPHA_MAX = 25.0  # [rad/s^2] control.yaml angular.z.max_acceleration
CMD_TIMEOUT = 0.5  # [s] the J100's cmd_vel timeout (the controller stops)


def _toward(value: float, target: float, step: float) -> float:
    return target if abs(target - value) <= step else value + math.copysign(step, target - value)


class JackalDevice(HostedDevice):
    """One simulated Jackal behind one robot's ``jackal`` driver, on the world's Zenoh session.

    ``namespace``: the robot's key prefix (default ``jackal/<fleet>/robot<id>`` from ``keys``,
    ``robot<id>`` without); it overrides the scenario's. ``on_malformed`` is told
    ``jackal/<counter>`` for each malformed command. The rest (``run_dir``, ``session``,
    ``keys``, ``seed``) are HostedDevice's; ``session`` is required.
    """

    kind = "jackal"

    def __init__(self, robot, *, namespace: str | None = None, on_malformed: Callable[[str], None] | None = None,
                 **kw):
        super().__init__(robot, **kw)
        if self.session is None:
            raise DeviceError(f"robot {robot.id}: the jackal device needs the world's zenoh session")
        if namespace is None:
            namespace = f"jackal/{self.keys.fleet}/robot{robot.id}" if self.keys is not None else f"robot{robot.id}"
        cfg = self.driver_config(JackalConfig, namespace=namespace)  # the topics as the driver has them, our namespace
        self._open_timeout = cfg.open_timeout
        self.namespace = namespace
        self.cmd_key = cfg.key(robot.id, cfg.cmd_topic)
        self.odom_key = cfg.key(robot.id, cfg.odom_topic)
        self.scan_key = cfg.key(robot.id, cfg.scan_topic)
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
        self._sub: Any = None
        self._pubs: dict[str, Any] = {}
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None

    # --- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        self._pubs = {k: self.session.declare_publisher(k, encoding=zenoh.Encoding.APPLICATION_CDR)
                      for k in (self.odom_key, self.scan_key)}
        self._sub = self.session.declare_subscriber(self.cmd_key, self._on_cmd)
        self._halt.clear()
        self._thread = threading.Thread(target=self._run_realtime, name=f"jackal-device-{self.robot_id}", daemon=True)
        self._thread.start()

    def driver_params(self) -> dict[str, Any]:
        return {"namespace": self.namespace, "open_timeout": max(self._open_timeout, SIM_OPEN_TIMEOUT_S)}

    def _stop_realtime(self) -> None:
        self._halt.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None

    def close(self) -> None:
        self._stop_realtime()
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        for pub in self._pubs.values():
            pub.undeclare()
        self._pubs = {}

    def _run_realtime(self) -> None:
        while not self._halt.wait(1.0 / ODOM_RATE):
            try:
                self._publish_odom(self.wall_time(), self.body)
            except zenoh.ZError as e:  # the world's session is gone: so is the robot
                log.warning("jackal device %s: odometry on %s stopped: %s", self.robot_id, self.odom_key, e)
                return

    # --- commands in --------------------------------------------------------------------
    def _on_cmd(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: queue the payload; on the wall clock the arrival is its device time."""
        arrived = None if self.in_lockstep else self.wall_time()
        with self._lock:
            self._pending.append((sample.payload.to_bytes(), arrived))

    def take_commands(self, t_sim: float) -> None:
        now = self.device_time(t_sim)
        if self._t is None:
            self._t = t_sim
        with self._lock:
            items = list(self._pending)
            self._pending.clear()
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
        v_std, w_std = self._odom_noise
        if v_std or w_std:
            nv, nw = self._rng.normal(0.0, 1.0, 2) * (v_std, w_std)
            body = replace(body, v=body.v + float(nv), w=body.w + float(nw))
        self.body = body
        if self.in_lockstep:  # one odometry per step; on the wall clock the thread sends them at 50 Hz
            self._publish_odom(self.device_time(t_sim_next), body)

    def publish_scan(self, t_sim: float, angle_min: float, angle_increment: float, range_max: float,
                     ranges: Sequence[float]) -> None:
        """The world's lidar scan at ``t_sim`` as the Jackal's ``sensor_msgs/LaserScan``."""
        pub = self._pubs.get(self.scan_key)
        if pub is not None:
            pub.put(encode_laserscan(self.device_time(t_sim), angle_min, angle_increment, range_max, ranges))
            self._count("scan")

    def fail(self) -> str:
        self.odom_stopped = True
        return "the Jackal's filtered odometry stopped (its EKF died); cmd_vel still reaches the controller"

    def _publish_odom(self, stamp: float, body: Body) -> None:
        pub = self._pubs.get(self.odom_key)
        if pub is not None and not self.odom_stopped:
            pub.put(encode_odometry(stamp, body.x, body.y, body.yaw, body.v, body.w))
            self._count("odom")
            self.odom_sent += 1

    # --- helpers ------------------------------------------------------------------------
    def _count(self, key: str) -> None:
        self.counters[key] = self.counters.get(key, 0) + 1

    def _malformed(self, kind: str) -> None:
        self._count(kind)
        self._on_malformed(f"jackal/{kind}")


__all__ = ["JackalDevice"]
