"""``jackal``: a Clearpath Jackal J100 (ROS 2) behind zenoh-bridge-ros2dds, without ROS on our side.

The robot's ROS 2 topics under its namespace are Zenoh keys without the leading slash
(``/robot2/cmd_vel`` is ``robot2/cmd_vel``) carrying CDR bytes (``stack.drivers.ros2cdr``):

- ``<ns>/cmd_vel`` (``geometry_msgs/Twist``): we publish linear.x = v, angular.z = w; the
  last one is resent every ``keepalive_period``, well inside the controller's 0.5 s
  ``cmd_vel`` timeout (after which the Jackal stops by itself);
- ``<ns>/platform/odom/filtered`` (``nav_msgs/Odometry``, the EKF's odom -> base_link):
  ``read()`` gives v = twist.linear.x, w = twist.angular.z, the header stamp and the pose
  (x, y, yaw from the quaternion);
- ``<ns>/sensors/lidar2d_0/scan`` (``sensor_msgs/LaserScan``): ``read_scan()``.

Commands are clamped to the robot's limits (the base class) and to the Jackal's own
controller limits (``v_max`` 2.0 m/s, ``w_max`` 4.0 rad/s), whichever is lower. Opening
waits up to ``open_timeout`` for the first odometry (is the bridge up, the namespace right?).

A fault (odometry older than ``odom_timeout`` on the driver's clock, after the first one)
sends a zero Twist and sets ``fault`` to a one-line reason; the base class then sends no
motion and the keepalive resends zero until the driver is closed and opened again.

Malformed traffic (not CDR, not the expected type, non-finite values) is counted in
``counters`` (``odom_not_cdr``, ``scan_bad_value``...) and told to ``on_malformed`` as
``jackal/<counter>``; nothing raises. Supervision (the keepalive, the odometry timeout, the
fault latch, ``counters``, ``liveness()``: ``odom``, ``scan``) is the base class's.

>>> drv = JackalDriver(2, DriverLimits(1.0, 2.0), JackalConfig(namespace="robot2"), session=s)  # doctest: +SKIP
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import zenoh

from .base import Driver, DriverError, DriverLimits, Keepalive, Odometry
from .ros2cdr import CdrError, LaserScanData, decode_laserscan, decode_odometry, encode_twist

log = logging.getLogger(__name__)

_KEY = re.compile(r"[^/*$?#\s]+(/[^/*$?#\s]+)*")  # concrete key-expression chunks: no wildcards, no empty chunk


def _check_key(name: str, value: Any) -> None:
    if not (isinstance(value, str) and _KEY.fullmatch(value)):
        raise ValueError(f"jackal driver: {name} {value!r} is not a key-expression prefix "
                         f"(chunks separated by '/', no leading or trailing '/', no '*', '$', '?', '#' or spaces)")


@dataclass(frozen=True)
class JackalConfig:
    """Where the Jackal's topics are on Zenoh and how the driver watches them (defaults: a J100's)."""

    namespace: str | None = None
    """The robot's ROS 2 namespace as a Zenoh key prefix, without the leading slash (``robot2``,
    ``j100_0421``); None: ``robot<id>``."""
    cmd_topic: str = "cmd_vel"
    """Twist commands, relative to the namespace."""
    odom_topic: str = "platform/odom/filtered"
    """The EKF-filtered odometry (odom -> base_link), relative to the namespace."""
    scan_topic: str = "sensors/lidar2d_0/scan"
    """The 2D lidar's scans, relative to the namespace."""
    odom_timeout: float = 0.5
    """[s] odometry older than this (after the first one) is a fault: 25 periods of the EKF's 50 Hz."""
    keepalive_period: float = 0.1
    """[s] the last Twist is resent this often (the controller stops 0.5 s after its last cmd_vel)."""
    open_timeout: float = 2.0
    """[s] how long opening waits for the first odometry; 0: do not wait."""
    v_max: float = 2.0
    """[m/s] the Jackal controller's speed limit (commands are clamped to it and to the robot's own)."""
    w_max: float = 4.0
    """[rad/s] the Jackal controller's turn-rate limit (commands are clamped to it and to the robot's own)."""

    def __post_init__(self):
        if self.namespace is not None:
            _check_key("namespace", self.namespace)
        for name in ("cmd_topic", "odom_topic", "scan_topic"):
            _check_key(name, getattr(self, name))
        for name in ("odom_timeout", "keepalive_period", "v_max", "w_max"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"jackal driver: {name} must be a positive number, not {value!r}")
        if not (isinstance(self.open_timeout, (int, float)) and math.isfinite(self.open_timeout)
                and self.open_timeout >= 0):
            raise ValueError(f"jackal driver: open_timeout must be a number >= 0, not {self.open_timeout!r}")
        if self.keepalive_period >= 0.5:
            raise ValueError("jackal driver: keepalive_period must be under 0.5 s (the controller's cmd_vel timeout)")

    def key(self, robot_id: int, topic: str) -> str:
        """The Zenoh key of a topic of robot ``robot_id``."""
        return f"{self.namespace or f'robot{robot_id}'}/{topic}"


class JackalDriver(Driver):
    """A ROS 2 Jackal's cmd_vel, filtered odometry and 2D scan over the agent's Zenoh session.

    ``session``: the agent's own Zenoh session (the driver declares on it, never opens one).
    ``clock`` times the odometry timeout (the agent's clock: wall time, or sim time in
    lock-step); the keepalive follows it or ``wall``, whichever is first; odometry is stamped
    with its ROS header stamp, so ``stamp`` is not used. ``**params`` are JackalConfig fields
    (the scenario's driver settings) that override ``config``. ``keys`` is the agent's common
    driver argument (not used); ``on_malformed`` is told ``jackal/<counter>`` for each
    malformed payload and ``on_odom`` gets each new odometry sample.
    """

    name = "jackal"
    config_class = JackalConfig
    provides_scan = True

    def __init__(self, robot_id: int, limits: DriverLimits, config: JackalConfig | None = None, *,
                 session: zenoh.Session, keys: Any = None, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.monotonic, stamp: Callable[[], float] = time.time,
                 on_odom: Callable[[Odometry], None] | None = None,
                 on_malformed: Callable[[str], None] | None = None, **params):
        super().__init__(robot_id, limits, clock, wall, on_malformed)
        self.config = self._configure(config, params)
        if session is None:
            raise ValueError("jackal driver: needs the agent's zenoh session")
        self._session = session
        self._on_odom = on_odom
        self.cmd_key = self.config.key(robot_id, self.config.cmd_topic)
        self.odom_key = self.config.key(robot_id, self.config.odom_topic)
        self.scan_key = self.config.key(robot_id, self.config.scan_topic)
        self._state = threading.Condition()  # guards _latest, _scan
        self._latest: Odometry | None = None
        self._scan: LaserScanData | None = None
        self._pub: Any = None
        self._declared: list = []  # the publisher and subscribers on the agent's session

    # --- lifecycle --------------------------------------------------------------------
    def _open(self) -> None:
        cfg = self.config
        with self._state:
            self._latest = self._scan = None
        try:
            self._declared += [self._session.declare_subscriber(self.odom_key, self._odom_cb),
                               self._session.declare_subscriber(self.scan_key, self._scan_cb)]
            self._pub = self._session.declare_publisher(self.cmd_key, encoding=zenoh.Encoding.APPLICATION_CDR,
                                                        congestion_control=zenoh.CongestionControl.BLOCK)
            self._declared.append(self._pub)
        except zenoh.ZError as e:
            self._teardown()
            raise DriverError(f"jackal driver {self.robot_id}: cannot declare {self.cmd_key} / {self.odom_key}: {e}") from e
        if cfg.open_timeout > 0:
            with self._state:
                if not self._state.wait_for(lambda: self._latest is not None, cfg.open_timeout):
                    self._teardown()
                    raise DriverError(f"jackal driver {self.robot_id}: no odometry on {self.odom_key} within "
                                      f"{cfg.open_timeout:g} s (is zenoh-bridge-ros2dds up, namespace right?)")

    def _close(self) -> None:
        self._stop_supervisor()
        self._teardown()

    def _teardown(self) -> None:
        self._pub = None
        while self._declared:
            self._declared.pop().undeclare()

    # --- commands ---------------------------------------------------------------------
    def clamp(self, v: float, w: float) -> tuple[float, float]:
        """The robot's limits (base class), then the Jackal controller's."""
        v, w = super().clamp(v, w)
        cfg = self.config
        return max(-cfg.v_max, min(cfg.v_max, v)), max(-cfg.w_max, min(cfg.w_max, w))

    def _send(self, v: float, w: float) -> None:
        pub = self._pub
        if pub is None:
            raise DriverError(f"jackal driver {self.robot_id}: {self.cmd_key} is not declared")
        try:
            pub.put(encode_twist(v, w))
        except zenoh.ZError as e:
            raise DriverError(f"jackal driver {self.robot_id}: put on {self.cmd_key} failed: {e}") from e
        self.count("tx")

    # --- receiving (zenoh callback threads) ---------------------------------------------
    def _odom_cb(self, sample: zenoh.Sample) -> None:
        odo = self._decode(sample, "odom", decode_odometry)
        if odo is None:
            return
        with self._state:
            self._latest = odo
            self._alive("odom")
            self.count("odom")
            self._state.notify_all()
        if self._on_odom is not None:
            self._on_odom(odo)

    def _scan_cb(self, sample: zenoh.Sample) -> None:
        scan = self._decode(sample, "scan", decode_laserscan)
        if scan is not None:
            with self._state:
                self._scan = scan
                self._alive("scan")
                self.count("scan")

    def _decode(self, sample: zenoh.Sample, stream: str, decode: Callable[[bytes], Any]) -> Any:
        try:
            return decode(sample.payload.to_bytes())
        except CdrError as e:
            self.count(f"{stream}_{e.kind}", malformed=True)
            log.debug("jackal driver %s: %s on %s: %s", self.robot_id, e.kind, sample.key_expr, e)
            return None

    def _read(self) -> Odometry | None:
        with self._state:
            return self._latest

    def read_scan(self) -> LaserScanData | None:
        """The newest scan, or None before the first."""
        with self._state:
            return self._scan

    # --- supervision hooks (the base's supervisor calls them) --------------------------
    @property
    def supervise_period(self) -> float:
        """A fifth of the odom_timeout (and 20 ms at most) between supervision rounds."""
        return min(0.02, self.config.odom_timeout / 5)

    def _keepalives(self) -> list[Keepalive]:
        """The last Twist, faulted or not: after a fault the controller keeps hearing zero."""
        return [Keepalive("command", self.config.keepalive_period, faulted=True)]

    def _health(self, now: float) -> str | None:
        """Odometry older than ``odom_timeout`` on the driver's clock (after the first one) is a fault."""
        age = self.age("odom", now)
        if age is not None and age > self.config.odom_timeout:
            return f"no odometry on {self.odom_key} for {age:.2f} s"
        return None


__all__ = ["JackalConfig", "JackalDriver", "LaserScanData"]
