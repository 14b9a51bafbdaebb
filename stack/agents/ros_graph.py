"""The fleet in the ROS graph (opt-in, ``robot.ros_graph``): an agent's estimate and formation target as
ROS 2 topics, and a new formation goal from a ROS 2 ``geometry_msgs/PoseStamped`` (docs/ros2.md).

With ``enabled: true`` the agent, on its own Zenoh session, under the namespace ``/<namespace>``
(default ``/robot<id>``):

- publishes ``<odom_topic>`` (``nav_msgs/Odometry``, default ``formation/odometry``): its EKF estimate in
  the site frame (header ``frame_id``, default ``map``, REP 105's world-fixed frame), child
  ``<namespace>/base_link``; pose x, y, yaw and twist v, w (body frame) with their covariances from the
  EKF's P (the (x, y, yaw) block at indices 0, 1, 5 of the 6 x 6 pose covariance, (v, w) at 0, 5 of the
  twist's; z, roll, pitch rows zero: planar);
- publishes ``<slot_topic>`` (``geometry_msgs/PoseStamped``, default ``formation/slot``): its formation
  target in the site frame, ``DecisionLayer.target`` (a follower: its slot of eq. 3 about the leader; the
  leader and an arrival-time peer: the goal), identity orientation (a slot is a position); nothing while a
  follower has no leader to follow;
- subscribes to ``<goal_topic>`` (``geometry_msgs/PoseStamped``, default ``goal_pose``, what RViz's
  "2D Goal Pose" and Nav2's tools send): a valid goal on the leader (or a peer) is its new goal from the
  next control step on (x, y; the orientation is not used); followers keep their slots about the leader.

Two transports (``transport``): ``bridge``, the keys zenoh-bridge-ros2dds gives ROS 2 topics (the topic
name without its leading ``/``, bare CDR); ``rmw_zenoh``, the ROS 2 node ``/<namespace>/<node_name>``
with rmw_zenoh's keys, attachments and liveliness tokens (``stack.drivers.rmw_zenoh``).

Publishing never blocks the control loop: :meth:`RosGraphLink.step` only hands the step's values to a
publisher thread (one slot: the newest wins, ``superseded`` counts those replaced unsent), ``rate_hz`` on
average on the agent's clock and at most once a control step; puts drop rather than wait on congestion.
Goals that cannot be used are counted drops, never raised: told to the agent's ``on_malformed`` as
``ros_graph/<counter>``
(``goal_not_cdr``, ``goal_undecodable``, ``goal_bad_value``, ``goal_wrong_frame``, ``goal_not_leader``;
on rmw_zenoh also ``rmw_no_attachment``, ``rmw_bad_attachment``, ``rmw_type_mismatch``,
``rmw_hash_mismatch``), each kind logged (at most once a second, with its count).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
import zenoh

from .. import settings
from ..drivers import rmw_zenoh
from ..drivers.ros2cdr import ODOMETRY, CdrError, encode_odometry
from ..settings import rule

log = logging.getLogger("stack.agent")

TRANSPORTS = ("bridge", "rmw_zenoh")
MAX_GOAL_M = 1e6  # a goal farther than this from the site origin is a bad value
LOG_EVERY_S = 1.0  # a drop kind is logged at most this often


@dataclass(frozen=True)
class RosGraphConfig:
    """``robot.ros_graph``: this agent's estimate, slot and goal as ROS 2 topics (off by default)."""

    enabled: bool = False
    """Publish the estimate and slot, take goals; false: nothing of this on the network."""
    transport: Literal["bridge", "rmw_zenoh"] = "bridge"
    """``bridge``: keys as zenoh-bridge-ros2dds maps ROS 2 topics (topic name, bare CDR); ``rmw_zenoh``: a ROS 2
    node with rmw_zenoh's keys, attachments and liveliness tokens (``ros2 node list`` shows it)."""
    domain_id: int = field(default=0, metadata=rule(">= 0", "<= 232"))
    """``rmw_zenoh``: the ROS_DOMAIN_ID, the first chunk of every key."""
    ros_distro: Literal["jazzy", "humble"] = "jazzy"
    """``rmw_zenoh``: ``jazzy`` (RIHS01 type hashes in the keys) or ``humble`` (``TypeHashNotSupported``)."""
    namespace: str | None = None
    """The ROS 2 namespace, without the leading slash (``robot2``, ``fleet_a/robot2``); None: ``robot<id>``."""
    node_name: str = "stack_formation"
    """``rmw_zenoh``: the node's name in the namespace (``ros2 node list``: ``/robot0/stack_formation``)."""
    odom_topic: str = "formation/odometry"
    """``nav_msgs/Odometry``: the agent's estimate in ``frame_id``; relative to the namespace, or absolute
    (``/...``)."""
    slot_topic: str = "formation/slot"
    """``geometry_msgs/PoseStamped``: the agent's formation target (its slot; the leader's: the goal) in
    ``frame_id``."""
    goal_topic: str = "goal_pose"
    """``geometry_msgs/PoseStamped`` goals taken by the leader (or a peer): relative (``/robot0/goal_pose``) or
    absolute (``/goal_pose``: one topic for every robot; only the leader takes it)."""
    frame_id: str = "map"
    """The site frame's ROS name (REP 105's ``map``): the header of what we publish; goals in another frame
    are dropped."""
    child_frame_id: str | None = None
    """The odometry's child frame; None: ``<namespace>/base_link``."""
    rate_hz: float = field(default=10.0, metadata=rule("> 0", "<= 100"))
    """[Hz] how often, on average on the agent's clock (sim time in lock-step), and at most once a control step."""

    def __post_init__(self):
        settings.check(self)
        if self.namespace is not None:
            try:
                rmw_zenoh.fully_qualified("/", self.namespace)
            except ValueError:
                raise ValueError(f"namespace: {self.namespace!r} is not a ROS 2 namespace without its leading '/' "
                                 "(tokens of letters, digits, '_' separated by '/')") from None
            if self.namespace.startswith("/"):
                raise ValueError(f"namespace: give it without the leading '/', e.g. {self.namespace.lstrip('/')!r}")
        if not rmw_zenoh.NAME.fullmatch(self.node_name):
            raise ValueError(f"node_name: {self.node_name!r} is not a ROS 2 node name (letters, digits, '_')")
        for name in ("odom_topic", "slot_topic", "goal_topic"):
            try:
                rmw_zenoh.fully_qualified("/", getattr(self, name))
            except ValueError:
                raise ValueError(f"{name}: {getattr(self, name)!r} is not a ROS 2 topic name "
                                 "(tokens of letters, digits, '_' separated by '/')") from None
        for name in ("frame_id", "child_frame_id"):
            value = getattr(self, name)
            if value is not None and (not value or any(c.isspace() for c in value)):
                raise ValueError(f"{name}: {value!r} is not a frame name (not empty, no spaces)")

    def resolved(self, robot_id: int) -> tuple[str, str]:
        """(namespace with its leading slash, child frame) for robot ``robot_id``."""
        ns = self.namespace or f"robot{robot_id}"
        return "/" + ns, self.child_frame_id or f"{ns}/base_link"


# --- transports ----------------------------------------------------------------------------
class _BridgeTransport:
    """zenoh-bridge-ros2dds' mapping: key = fully qualified topic without the leading ``/``, payload bare CDR."""

    def __init__(self, session: zenoh.Session, namespace: str):
        self._session, self._ns = session, namespace
        self._declared: list = []

    def key(self, topic: str) -> str:
        return rmw_zenoh.fully_qualified(self._ns, topic).strip("/")

    def publisher(self, topic: str, ros_type: str) -> Callable[[bytes], None]:
        pub = self._session.declare_publisher(self.key(topic), encoding=zenoh.Encoding.APPLICATION_CDR,
                                              congestion_control=zenoh.CongestionControl.DROP)
        self._declared.append(pub)
        return pub.put

    def subscribe(self, topic: str, ros_type: str, callback: Callable[[bytes], None]) -> None:
        self._declared.append(self._session.declare_subscriber(
            self.key(topic), lambda sample: callback(sample.payload.to_bytes())))

    def close(self) -> None:
        while self._declared:
            self._declared.pop().undeclare()


class _RmwTransport:
    """rmw_zenoh: our node ``/<namespace>/<node_name>``, its publishers and subscription with their tokens."""

    def __init__(self, session: zenoh.Session, cfg: RosGraphConfig, namespace: str,
                 on_malformed: Callable[[str], None]):
        self.node = rmw_zenoh.RmwZenohNode(
            session, rmw_zenoh.NodeConfig(name=cfg.node_name, namespace=namespace, domain_id=cfg.domain_id,
                                          distro=cfg.ros_distro),
            on_malformed=lambda kind: on_malformed(f"rmw_{kind}"))

    def publisher(self, topic: str, ros_type: str) -> Callable[[bytes], None]:
        return self.node.publisher(topic, ros_type, block=False).put

    def subscribe(self, topic: str, ros_type: str, callback: Callable[[bytes], None]) -> None:
        self.node.subscribe(topic, ros_type, lambda payload, att: callback(payload))

    def close(self) -> None:
        self.node.close()


# --- what is published ----------------------------------------------------------------------
@dataclass(frozen=True)
class _Snapshot:
    """One control step's values, as the publisher thread encodes them."""

    stamp: float
    pose: tuple[float, float, float, float, float]  # x, y, yaw, v, w
    P: np.ndarray  # the EKF's 5 x 5 covariance of (x, y, yaw, v, w)
    target: tuple[float, float] | None


def covariances(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The EKF's 5 x 5 P over (x, y, yaw, v, w) as ROS 2's row-major 6 x 6 pose and twist covariances
    (axes x, y, z, roll, pitch, yaw; the twist's linear.x = v and angular.z = w)."""
    pose, twist = np.zeros((6, 6)), np.zeros((6, 6))
    pi = [0, 1, 5]
    pose[np.ix_(pi, pi)] = P[:3, :3]
    twist[np.ix_([0, 5], [0, 5])] = P[3:5, 3:5]
    return pose.ravel(), twist.ravel()


class RosGraphLink:
    """One agent's estimate, slot and goal subscription in the ROS graph (see the module docstring)."""

    def __init__(self, cfg: RosGraphConfig, robot_id: int, session: zenoh.Session,
                 on_malformed: Callable[[str], None] | None = None):
        self.cfg = cfg
        self.namespace, self.child_frame_id = cfg.resolved(robot_id)
        self.counters: dict[str, int] = {}
        self._on_malformed = on_malformed or (lambda key: None)
        self._lock = threading.Condition()
        self._logged: dict[str, float] = {}
        self._pending: _Snapshot | None = None
        self._goal: tuple[float, float] | None = None
        self._next_t: float | None = None
        self._stop = False
        self.transport = (_RmwTransport(session, cfg, self.namespace, self._drop) if cfg.transport == "rmw_zenoh"
                          else _BridgeTransport(session, self.namespace))
        self._put_odom = self.transport.publisher(cfg.odom_topic, ODOMETRY)
        self._put_slot = self.transport.publisher(cfg.slot_topic, rmw_zenoh.POSE_STAMPED)
        self.transport.subscribe(cfg.goal_topic, rmw_zenoh.POSE_STAMPED, self._on_goal)
        self._thread = threading.Thread(target=self._publish_loop, name=f"ros-graph-{robot_id}", daemon=True)
        self._thread.start()
        log.info("agent %d: in the ROS graph (%s) as %s: %s, %s; goals on %s, frame %s", robot_id, cfg.transport,
                 self.namespace, *(rmw_zenoh.fully_qualified(self.namespace, t)
                                   for t in (cfg.odom_topic, cfg.slot_topic, cfg.goal_topic)), cfg.frame_id)

    # --- the control loop's side (never blocks) ------------------------------------------------
    def step(self, t: float, stamp: float, pipeline) -> None:
        """After control step at time ``t`` (agent clock; ``stamp`` the header's): hand over its estimate and
        target (at most ``rate_hz``). A goal received goes in through the next step's inputs (:meth:`take_goal`)."""
        if not self._due(t):
            return
        ekf, target = pipeline.estimator, pipeline.decision.target
        p = ekf.pose
        snap = _Snapshot(stamp, (p.x, p.y, p.yaw, p.v, p.w), ekf.P,
                         None if target is None else (float(target[0]), float(target[1])))
        with self._lock:
            if self._pending is not None:
                self._count("superseded")
            self._pending = snap
            self._lock.notify()

    def _due(self, t: float) -> bool:
        """Whether step time ``t`` publishes: on a grid of 1 / ``rate_hz`` (the average rate is ``rate_hz`` whatever
        the loop's jitter, a quarter period's leeway), started again after a stall rather than catching up."""
        period = 1.0 / self.cfg.rate_hz
        if self._next_t is not None and t < self._next_t - 0.25 * period:
            return False
        late = self._next_t is None or t > self._next_t + period
        self._next_t = t + period if late else self._next_t + period
        return True

    def take_goal(self, pipeline) -> tuple[float, float] | None:
        """The goal received since the last step, for the next step's inputs (``StepInputs.goal``: a step's log
        then holds it, and a replay applies it at the same step); None if none, or not for this robot's role."""
        with self._lock:
            goal, self._goal = self._goal, None
        if goal is None:
            return None
        if pipeline.role not in ("leader", "peer"):
            self._drop("goal_not_leader", f"goal {goal} for a {pipeline.role}: send goals to the leader")
            return None
        self._count("goal_applied")
        log.info("agent %s: new goal (%.2f, %.2f) from %s", pipeline.id, *goal,
                 rmw_zenoh.fully_qualified(self.namespace, self.cfg.goal_topic))
        return goal

    # --- the publisher thread ------------------------------------------------------------------
    def _publish_loop(self) -> None:
        while True:
            with self._lock:
                while self._pending is None and not self._stop:
                    self._lock.wait()
                if self._stop:
                    return
                snap, self._pending = self._pending, None
            self._publish(snap)

    def _publish(self, s: _Snapshot) -> None:
        x, y, yaw, v, w = s.pose
        pose_cov, twist_cov = covariances(s.P)
        try:
            self._put_odom(encode_odometry(s.stamp, x, y, yaw, v, w, frame_id=self.cfg.frame_id,
                                           child_frame_id=self.child_frame_id, pose_covariance=pose_cov,
                                           twist_covariance=twist_cov))
            if s.target is not None:
                self._put_slot(rmw_zenoh.encode_pose_stamped(s.stamp, *s.target, 0.0, frame_id=self.cfg.frame_id))
        except Exception as e:  # noqa: BLE001 - a closing session, a broken link: counted, the loop goes on
            self._count("publish_errors")
            self._log("publish_errors", f"cannot publish: {type(e).__name__}: {e}")
            return
        self._count("published")

    # --- goals (Zenoh's threads) -----------------------------------------------------------------
    def _on_goal(self, payload: bytes) -> None:
        try:
            g = rmw_zenoh.decode_pose_stamped(payload)
        except CdrError as e:
            self._drop(f"goal_{e.kind}", f"goal dropped: {e}")
            return
        if g.frame_id != self.cfg.frame_id:
            self._drop("goal_wrong_frame", f"goal in frame {g.frame_id!r} dropped: goals are in {self.cfg.frame_id!r}")
            return
        if not (abs(g.x) <= MAX_GOAL_M and abs(g.y) <= MAX_GOAL_M):
            self._drop("goal_bad_value", f"goal ({g.x:g}, {g.y:g}) dropped: farther than {MAX_GOAL_M:g} m")
            return
        with self._lock:
            self._goal = (g.x, g.y)
            self._count("goal_received")

    # --- counting --------------------------------------------------------------------------------
    def _count(self, kind: str, n: int = 1) -> int:
        """Caller may hold the lock (it is re-entrant)."""
        with self._lock:
            self.counters[kind] = self.counters.get(kind, 0) + n
            return self.counters[kind]

    def _drop(self, kind: str, what: str | None = None) -> None:
        """A sample not used: counted here and told to the agent (``ros_graph/<kind>``), logged."""
        self._count(kind)
        self._on_malformed(f"ros_graph/{kind}")
        self._log(kind, what or f"{kind.replace('_', ' ')}")

    def _log(self, kind: str, what: str) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._logged.get(kind, -math.inf) < LOG_EVERY_S:
                return
            self._logged[kind] = now
            n = self.counters.get(kind, 0)
        log.warning("ROS graph %s: %s (%s: %d so far)", self.namespace, what, kind, n)

    def close(self) -> None:
        """Stop the publisher thread, then undeclare everything (on rmw_zenoh the node leaves the graph)."""
        with self._lock:
            self._stop = True
            self._lock.notify()
        self._thread.join(5.0)
        self.transport.close()


def open_ros_graph(robot, session: zenoh.Session, on_malformed: Callable[[str], None]) -> RosGraphLink | None:
    """The robot's link into the ROS graph where its ``robot.ros_graph`` is enabled; None otherwise."""
    cfg = getattr(robot, "ros_graph", None)
    if cfg is None or not cfg.enabled:
        return None
    return RosGraphLink(cfg, robot.id, session, on_malformed)


__all__ = ["RosGraphConfig", "RosGraphLink", "TRANSPORTS", "covariances", "open_ros_graph"]
