"""``jackal``: a Clearpath Jackal J100 (ROS 2) over Zenoh, without ROS on our side.

Two transports (``transport``):

- ``bridge`` (the default): behind zenoh-bridge-ros2dds, the robot's ROS 2 topics under its
  namespace are Zenoh keys without the leading slash (``/robot2/cmd_vel`` is ``robot2/cmd_vel``)
  carrying bare CDR bytes (``stack.drivers.ros2cdr``);
- ``rmw_zenoh``: the robot runs ROS 2's Zenoh middleware (``rmw_zenoh_cpp``) and its router
  ``rmw_zenohd``, which the agent's session connects to (``--connect`` / ``--zenoh-config``); the
  driver is then the ROS 2 node ``/<namespace>/<node_name>`` (``stack.drivers.rmw_zenoh``): rmw_zenoh's
  keys (``<domain_id>/<namespace>/<topic>/<DDS type>/<type hash>``), an attachment on every
  ``cmd_vel`` sample, liveliness tokens that put it in the robot's ROS graph (``ros2 node list``), and
  samples without a valid attachment, or of another type or hash, dropped and counted
  (``rmw_no_attachment``, ``rmw_bad_attachment``, ``rmw_type_mismatch``, ``rmw_hash_mismatch``;
  ``rmw_lost`` counts gaps in the robot's sequence numbers, ``node.counters['lost']`` the samples
  missing). See docs/ros2.md and docs/deploy.md.

The topics, relative to the namespace, and what they carry (CDR on both transports):

- ``<ns>/cmd_vel`` (``geometry_msgs/Twist``): we publish linear.x = v, angular.z = w; the
  last one is resent every ``keepalive_period``, well inside the controller's 0.5 s
  ``cmd_vel`` timeout (after which the Jackal stops by itself);
- ``<ns>/platform/odom/filtered`` (``nav_msgs/Odometry``, the EKF's odom -> base_link):
  ``read()`` gives v = twist.linear.x, w = twist.angular.z, the header stamp and the pose
  (x, y, yaw from the quaternion);
- ``<ns>/sensors/lidar2d_0/scan`` (``sensor_msgs/LaserScan``): ``read_scan()``.

Commands are clamped to the robot's limits (the base class) and to the Jackal's own
controller limits (``v_max`` 2.0 m/s, ``w_max`` 4.0 rad/s), whichever is lower. Opening
waits up to ``open_timeout`` for the first odometry (is the bridge or rmw_zenohd up, the namespace
right?).

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

from . import rmw_zenoh
from .base import Driver, DriverError, DriverLimits, Keepalive, Odometry
from .ros2cdr import LASER_SCAN, ODOMETRY, TWIST, CdrError, LaserScanData, decode_laserscan, decode_odometry
from .ros2cdr import encode_twist

log = logging.getLogger(__name__)

_KEY = re.compile(r"[^/*$?#\s]+(/[^/*$?#\s]+)*")  # concrete key-expression chunks: no wildcards, no empty chunk


def _check_key(name: str, value: Any) -> None:
    if not (isinstance(value, str) and _KEY.fullmatch(value)):
        raise ValueError(f"jackal driver: {name} {value!r} is not a key-expression prefix "
                         f"(chunks separated by '/', no leading or trailing '/', no '*', '$', '?', '#' or spaces)")


TRANSPORTS = ("bridge", "rmw_zenoh")
_PEER = {"bridge": "zenoh-bridge-ros2dds", "rmw_zenoh": "the robot's rmw_zenohd"}


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
    transport: str = "bridge"
    """``bridge``: the robot's topics as zenoh-bridge-ros2dds shows them (keys = topic names, bare CDR);
    ``rmw_zenoh``: the robot runs rmw_zenoh_cpp and we are a ROS 2 node on its router (docs/ros2.md)."""
    domain_id: int = 0
    """``rmw_zenoh``: the robot's ROS_DOMAIN_ID (0..232), the first chunk of every key."""
    ros_distro: str = "jazzy"
    """``rmw_zenoh``: the robot's ROS 2 distribution, ``jazzy`` (RIHS01 type hashes in the keys) or
    ``humble`` (``TypeHashNotSupported``)."""
    node_name: str = "stack_agent"
    """``rmw_zenoh``: our node's name in the robot's namespace (``ros2 node list``: ``/robot2/stack_agent``)."""

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
        if self.transport not in TRANSPORTS:
            raise ValueError(f"jackal driver: transport {self.transport!r} is not one of {', '.join(TRANSPORTS)}")
        if isinstance(self.domain_id, bool) or not (isinstance(self.domain_id, int) and 0 <= self.domain_id <= 232):
            raise ValueError(f"jackal driver: domain_id must be an integer 0..232, not {self.domain_id!r}")
        if self.ros_distro not in rmw_zenoh.DISTROS:
            raise ValueError(f"jackal driver: ros_distro {self.ros_distro!r} is not one of "
                             f"{', '.join(rmw_zenoh.DISTROS)}")
        if self.transport == "rmw_zenoh":  # a bridge's key prefix need not be a ROS name; rmw_zenoh's must
            try:
                node = self.node_config(0)
                for topic in (self.cmd_topic, self.odom_topic, self.scan_topic):
                    rmw_zenoh.fully_qualified(node.namespace, topic)
            except ValueError as e:
                raise ValueError(f"jackal driver (transport rmw_zenoh): {e}") from None
        elif not (isinstance(self.node_name, str) and rmw_zenoh.NAME.fullmatch(self.node_name)):
            raise ValueError(f"jackal driver: node_name {self.node_name!r} is not a ROS 2 node name "
                             "(letters, digits, '_')")

    def key(self, robot_id: int, topic: str) -> str:
        """The bridge's Zenoh key of a topic of robot ``robot_id`` (its ROS 2 name without the leading slash)."""
        return f"{self.namespace or f'robot{robot_id}'}/{topic}"

    def node_config(self, robot_id: int, name: str | None = None) -> rmw_zenoh.NodeConfig:
        """``rmw_zenoh``: a node (ours, or ``name``) in robot ``robot_id``'s namespace, domain and distro."""
        return rmw_zenoh.NodeConfig(name=name or self.node_name, namespace=f"/{self.namespace or f'robot{robot_id}'}",
                                    domain_id=self.domain_id, distro=self.ros_distro)

    def topic_key(self, robot_id: int, topic: str, ros_type: str) -> str:
        """The Zenoh key of a topic on this transport: the bridge's, or rmw_zenoh's data key."""
        if self.transport == "bridge":
            return self.key(robot_id, topic)
        node = self.node_config(robot_id)
        return rmw_zenoh.topic_key(self.domain_id, rmw_zenoh.fully_qualified(node.namespace, topic), ros_type,
                                   self.ros_distro)


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
        cfg = self.config
        self.cmd_key = cfg.topic_key(robot_id, cfg.cmd_topic, TWIST)
        self.odom_key = cfg.topic_key(robot_id, cfg.odom_topic, ODOMETRY)
        self.scan_key = cfg.topic_key(robot_id, cfg.scan_topic, LASER_SCAN)
        self._state = threading.Condition()  # guards _latest, _scan
        self._latest: Odometry | None = None
        self._scan: LaserScanData | None = None
        self._pub: Any = None  # a zenoh Publisher (bridge) or an RmwPublisher: put(payload) either way
        self._declared: list = []  # the publisher and subscribers on the agent's session, or our rmw_zenoh node
        self.node: rmw_zenoh.RmwZenohNode | None = None  # rmw_zenoh: our ROS 2 node while open

    # --- lifecycle --------------------------------------------------------------------
    def _open(self) -> None:
        cfg = self.config
        with self._state:
            self._latest = self._scan = None
        try:
            if cfg.transport == "rmw_zenoh":
                self._open_node()
            else:
                self._open_bridge()
        except zenoh.ZError as e:
            self._teardown()
            raise DriverError(f"jackal driver {self.robot_id}: cannot declare {self.cmd_key} / {self.odom_key}: {e}") from e
        if cfg.open_timeout > 0:
            with self._state:
                if not self._state.wait_for(lambda: self._latest is not None, cfg.open_timeout):
                    self._teardown()
                    raise DriverError(f"jackal driver {self.robot_id}: no odometry on {self.odom_key} within "
                                      f"{cfg.open_timeout:g} s (is {_PEER[cfg.transport]} up, namespace right?)")

    def _open_bridge(self) -> None:
        """zenoh-bridge-ros2dds: plain subscribers and a publisher on the topic names."""
        s = self._session
        for key, handle in ((self.odom_key, self._odom_payload), (self.scan_key, self._scan_payload)):
            self._declared.append(s.declare_subscriber(key, lambda x, h=handle: h(x.payload.to_bytes(), x.key_expr)))
        self._pub = s.declare_publisher(self.cmd_key, encoding=zenoh.Encoding.APPLICATION_CDR,
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        self._declared.append(self._pub)

    def _open_node(self) -> None:
        """rmw_zenoh: our node in the robot's namespace; its endpoints check and write attachments."""
        cfg = self.config
        self.node = node = rmw_zenoh.RmwZenohNode(self._session, cfg.node_config(self.robot_id),
                                                  on_malformed=self._rmw_malformed)
        self._declared.append(node)
        node.subscribe(cfg.odom_topic, ODOMETRY, lambda payload, att: self._odom_payload(payload, self.odom_key))
        node.subscribe(cfg.scan_topic, LASER_SCAN, lambda payload, att: self._scan_payload(payload, self.scan_key),
                       qos=rmw_zenoh.SENSOR_QOS)
        self._pub = node.publisher(cfg.cmd_topic, TWIST, block=True)  # as on the bridge: a command waits, never drops

    def _rmw_malformed(self, kind: str) -> None:
        """The node dropped a sample (``kind``: no_attachment, bad_attachment, ...) or saw a gap (``lost``)."""
        self.count(f"rmw_{kind}", malformed=kind != "lost")

    def _close(self) -> None:
        self._stop_supervisor()
        self._teardown()

    def _teardown(self) -> None:
        self._pub = self.node = None
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

    # --- receiving (zenoh callback threads): the payloads of either transport ------------
    def _odom_payload(self, payload: bytes, key: Any) -> None:
        odo = self._decode(payload, key, "odom", decode_odometry)
        if odo is None:
            return
        with self._state:
            self._latest = odo
            self._alive("odom")
            self.count("odom")
            self._state.notify_all()
        if self._on_odom is not None:
            self._on_odom(odo)

    def _scan_payload(self, payload: bytes, key: Any) -> None:
        scan = self._decode(payload, key, "scan", decode_laserscan)
        if scan is not None:
            with self._state:
                self._scan = scan
                self._alive("scan")
                self.count("scan")

    def _decode(self, payload: bytes, key: Any, stream: str, decode: Callable[[bytes], Any]) -> Any:
        try:
            return decode(payload)
        except CdrError as e:
            self.count(f"{stream}_{e.kind}", malformed=True)
            log.debug("jackal driver %s: %s on %s: %s", self.robot_id, e.kind, key, e)
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


__all__ = ["JackalConfig", "JackalDriver", "LaserScanData", "TRANSPORTS"]
