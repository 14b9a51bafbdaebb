"""ROS 2 over Zenoh without a bridge: the wire conventions of ``rmw_zenoh_cpp`` (Jazzy, Humble).

Checked against rmw_zenoh_cpp's source as released for Jazzy (0.2.10) and Humble (0.1.9):
``src/detail/liveliness_utils.cpp``, ``attachment_helpers.cpp``, ``rmw_publisher_data.cpp``,
``rmw_subscription_data.cpp``, ``qos.cpp``, ``type_support_common.cpp`` and ``docs/design.md``.

- **Data keys** (``TopicInfo``): ``<domain_id>/<fully qualified topic, no leading />/<DDS type>/<type hash>``,
  e.g. ``0/robot2/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45...8d2a``. The DDS type name is
  ``<pkg>::msg::dds_::<Name>_``; the hash is the type's RIHS01 hash (REP 2011, :func:`type_hash`) on
  Jazzy and the constant ``TypeHashNotSupported`` on Humble. Payloads are CDR (``stack.drivers.ros2cdr``).
- **Attachment** on every sample (``AttachmentData::serialize_to_zbytes``, zenoh-ext serialisation):
  sequence number (int64 LE), source timestamp (int64 LE, ns since the epoch), the publisher's GID as a
  sequence of 16 bytes (LEB128 length ``0x10``, then the bytes): 33 bytes. rmw_zenoh_cpp drops a sample
  without one ("Unable to obtain attachment"); sequence numbers start at 1 per publisher and a gap counts
  as lost messages. rmw_zenoh Jazzy 0.2.0-0.2.3 and Humble 0.1.0-0.1.1 wrote each value after its
  name (``"sequence_number"``, ``"source_timestamp"``, ``"source_gid"``, zenoh-ext strings): both layouts
  are read; ``Attachment.encode(keyed=True)`` writes the old one for robots on those releases.
- **Graph** (``liveliness::Entity``): liveliness tokens
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node name>``
  and, for endpoints, ``/<topic>/<DDS type>/<type hash>/<qos>``; names mangled (``/`` -> ``%``), the QoS in
  rmw_zenoh's compact form (:class:`Qos`). ``ros2 node list`` and ``ros2 topic info`` read these.

rmw_zenoh derives a GID from an XXH3-128 hash of the entity's token; nothing on the receiving side
recomputes it (it is an opaque per-publisher id for message info and loss detection), so ours is the
first 16 bytes of the token's SHA-256: stable for the publisher's life and unique with the token.

:class:`RmwZenohNode` puts these together over an open Zenoh session (``stack.comm.session``)::

    node = RmwZenohNode(session, NodeConfig(name="stack_agent", namespace="/robot2"))
    cmd = node.publisher("cmd_vel", "geometry_msgs/msg/Twist")
    node.subscribe("platform/odom/filtered", "nav_msgs/msg/Odometry", on_odom)   # on_odom(payload, attachment)
    cmd.put(encode_twist(0.2, 0.0))

Malformed traffic never raises: samples without a valid attachment, on the topic with another type or
type hash, and liveliness tokens that do not parse are dropped and counted (``counters``, ``on_malformed``).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import math
import re
import struct
import threading
import time
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import zenoh
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.base import Nodetype

from .ros2cdr import CdrError, deserialize, quaternion_yaw, ros_time, serialize, yaw_quaternion
from .ros2cdr import TYPESTORE as _CDR_TYPES

log = logging.getLogger(__name__)

DISTROS = ("jazzy", "humble")
HASH_NOT_SUPPORTED = "TypeHashNotSupported"
"""The type-hash field of rmw_zenoh on Humble, which has no type hashes."""
ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
GID_SIZE = 16
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
"""A ROS 2 node name (one token)."""
_TOPIC = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
_NAMESPACE = re.compile(r"/|(/[A-Za-z_][A-Za-z0-9_]*)+")
_ROS_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/msg/([A-Za-z][A-Za-z0-9_]*)")


class RmwZenohError(ValueError):
    """A key, token, attachment or QoS string that is not rmw_zenoh's; ``kind`` names the counter."""

    def __init__(self, kind: str, what: str):
        super().__init__(what)
        self.kind = kind


# --- names ---------------------------------------------------------------------------------
def mangle(name: str) -> str:
    """rmw_zenoh's ``mangle_name``: every ``/`` becomes ``%`` (one key chunk per name)."""
    return name.replace("/", "%")


def demangle(name: str) -> str:
    return name.replace("%", "/")


def fully_qualified(namespace: str, topic: str) -> str:
    """A topic name resolved in a node's namespace (``/robot2`` + ``cmd_vel`` -> ``/robot2/cmd_vel``)."""
    if not (isinstance(topic, str) and _TOPIC.fullmatch(topic)):
        raise ValueError(f"rmw_zenoh: topic {topic!r} is not a ROS 2 topic name (tokens of letters, digits, '_')")
    if topic.startswith("/"):
        return topic
    return f"{namespace.rstrip('/')}/{topic}"


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/Twist`` -> ``geometry_msgs::msg::dds_::Twist_`` (rmw_zenoh's ``_create_type_name``)."""
    m = _ROS_TYPE.fullmatch(ros_type) if isinstance(ros_type, str) else None
    if m is None:
        raise ValueError(f"rmw_zenoh: {ros_type!r} is not a message type (package/msg/Name)")
    return f"{m.group(1)}::msg::dds_::{m.group(2)}_"


# --- type hashes (REP 2011, rosidl_generator_type_description) ----------------------------
_JAZZY = get_typestore(Stores.ROS2_JAZZY)
_BASE_TYPE_IDS = {"int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8, "uint64": 9,
                  "float32": 10, "float64": 11, "float128": 12, "char": 13, "wchar": 14, "bool": 15, "byte": 16,
                  "string": 17, "wstring": 18}
"""type_description_interfaces/msg/FieldType ids (FIELD_TYPE_*); 1 is a nested type."""
_BOUNDED_STRING_IDS = {"string": 21, "wstring": 22}
_ARRAY, _BOUNDED_SEQUENCE, _UNBOUNDED_SEQUENCE = 48, 96, 144
"""Offsets of FIELD_TYPE_*_ARRAY, *_BOUNDED_SEQUENCE and *_UNBOUNDED_SEQUENCE from the element's id."""


def _field_type(spec) -> dict:
    """A rosbags field definition as ``type_description_interfaces/msg/FieldType`` (dict, rosidl's key order)."""
    nodetype, detail = spec
    offset = capacity = 0
    if nodetype in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        (nodetype, detail), capacity = detail
        offset = _ARRAY if spec[0] == Nodetype.ARRAY else _BOUNDED_SEQUENCE if capacity else _UNBOUNDED_SEQUENCE
    if nodetype == Nodetype.NAME:
        type_id, string_capacity, nested = 1, 0, detail
    else:
        base, string_capacity = detail
        type_id = _BOUNDED_STRING_IDS[base] if string_capacity and base in _BOUNDED_STRING_IDS else _BASE_TYPE_IDS[base]
        nested = ""
    return {"type_id": type_id + offset, "capacity": capacity, "string_capacity": string_capacity,
            "nested_type_name": nested}


def _description(store, typename: str) -> tuple[dict, set[str]]:
    """``IndividualTypeDescription`` of one type (fields only; hashing drops default values) and what it names."""
    fields_ = []
    nested = set()
    for name, spec in store.fielddefs[typename][1]:
        ftype = _field_type(spec)
        fields_.append({"name": name, "type": ftype})
        if ftype["nested_type_name"]:
            nested.add(ftype["nested_type_name"])
    return {"type_name": typename, "fields": fields_}, nested


def type_description(typename: str, store=_JAZZY) -> dict:
    """``TypeDescription``: the type and every type it refers to, directly or not, sorted by name."""
    if typename not in store.fielddefs:
        raise ValueError(f"rmw_zenoh: no message definition for {typename!r}")
    main, todo = _description(store, typename)
    refs: dict[str, dict] = {}
    while todo:
        name = todo.pop()
        if name not in refs:
            refs[name], more = _description(store, name)
            todo |= more - refs.keys()
    return {"type_description": main, "referenced_type_descriptions": [refs[k] for k in sorted(refs)]}


@lru_cache(maxsize=None)
def rihs01(typename: str) -> str:
    """The RIHS01 hash of a message type (Jazzy definitions): sha256 of its type description as rosidl's JSON."""
    text = json.dumps(type_description(typename), ensure_ascii=True, allow_nan=False, separators=(", ", ": "))
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def type_hash(ros_type: str, distro: str = "jazzy") -> str:
    """The type-hash chunk rmw_zenoh puts in keys and tokens: RIHS01 on Jazzy, ``TypeHashNotSupported`` on Humble."""
    dds_type_name(ros_type)  # validates the name
    if distro not in DISTROS:
        raise ValueError(f"rmw_zenoh: ros_distro {distro!r} is not one of {', '.join(DISTROS)}")
    return HASH_NOT_SUPPORTED if distro == "humble" else rihs01(ros_type)


def topic_key(domain_id: int, fq_topic: str, ros_type: str, distro: str = "jazzy") -> str:
    """The data key of a topic: ``<domain>/<topic without leading and trailing />/<DDS type>/<hash>``."""
    return f"{domain_id}/{fq_topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash(ros_type, distro)}"


# --- QoS as rmw_zenoh encodes it in tokens -------------------------------------------------
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC, MANUAL_BY_TOPIC = 1, 3
INFINITE = (9223372036, 854775807)
"""RMW_DURATION_INFINITE as (sec, nsec)."""
_POLICY_VALUES = {"reliability": (0, 1, 2, 3, 4), "durability": (0, 1, 2, 3, 4), "history": (0, 1, 2, 3),
                  "liveliness": (0, 1, 3, 4, 5)}
"""The rmw enum values rmw_zenoh's ``str_to_qos_*`` maps accept."""


@dataclass(frozen=True)
class Qos:
    """An endpoint's QoS after rmw_zenoh's ``best_available_qos`` (defaults: rmw_zenoh's own, depth 42).

    In a token each policy that equals the default is left empty (``qos_to_keyexpr``):
    ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>``.
    """

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = AUTOMATIC
    liveliness_lease: tuple[int, int] = INFINITE

    def encode(self) -> str:
        d = _DEFAULT_QOS

        def part(name: str) -> str:
            value = getattr(self, name)
            return "" if value == getattr(d, name) else str(value)

        def pair(name: str) -> str:
            value, default = getattr(self, name), getattr(d, name)
            return ",".join("" if v == dv else str(v) for v, dv in zip(value, default))

        return (f"{part('reliability')}:{part('durability')}:{part('history')},{part('depth')}:{pair('deadline')}:"
                f"{pair('lifespan')}:{part('liveliness')},{pair('liveliness_lease')}")

    @classmethod
    def decode(cls, text: str) -> "Qos":
        """rmw_zenoh's ``keyexpr_to_qos``; :class:`RmwZenohError` (``bad_qos``) where it would fail."""
        parts = text.split(":")
        sub = [p.split(",") for p in parts[2:6]] if len(parts) >= 6 else []
        if len(sub) < 4 or min(len(s) for s in sub[:3]) < 2 or len(sub[3]) < 3:
            raise RmwZenohError("bad_qos", f"QoS {text!r}: not six ':'-separated policies")
        d = _DEFAULT_QOS
        num = _qos_number
        return cls(reliability=num(parts[0], d.reliability, text, "reliability"),
                   durability=num(parts[1], d.durability, text, "durability"),
                   history=num(sub[0][0], d.history, text, "history"), depth=num(sub[0][1], d.depth, text),
                   deadline=(num(sub[1][0], d.deadline[0], text), num(sub[1][1], d.deadline[1], text)),
                   lifespan=(num(sub[2][0], d.lifespan[0], text), num(sub[2][1], d.lifespan[1], text)),
                   liveliness=num(sub[3][0], d.liveliness, text, "liveliness"),
                   liveliness_lease=(num(sub[3][1], d.liveliness_lease[0], text),
                                     num(sub[3][2], d.liveliness_lease[1], text)))


def _qos_number(s: str, default: int, text: str, policy: str | None = None) -> int:
    if s == "":
        return default
    if not s.isdigit() or int(s) >= 2 ** 64 or (policy and int(s) not in _POLICY_VALUES[policy]):
        raise RmwZenohError("bad_qos", f"QoS {text!r}: {s!r} is not a valid {policy or 'number'}")
    return int(s)


_DEFAULT_QOS = Qos()
DEFAULT_QOS = Qos(depth=10)
"""rclcpp's ``QoS(10)`` (reliable, volatile, keep last 10), as most ROS 2 nodes publish and subscribe."""
SENSOR_QOS = Qos(reliability=BEST_EFFORT, depth=5)
"""rclcpp's ``SensorDataQoS`` (best effort, keep last 5)."""


# --- liveliness tokens ---------------------------------------------------------------------
@dataclass(frozen=True)
class GraphEntity:
    """One liveliness token of the ROS graph, parsed: a node or one of its endpoints."""

    domain_id: int
    zid: str
    node_id: str
    entity_id: str
    kind: str
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    type_name: str | None = None
    type_hash: str | None = None
    qos: Qos | None = None

    @property
    def node(self) -> str:
        """The node's fully qualified name, as ``ros2 node list`` prints it."""
        return f"{self.namespace.rstrip('/')}/{self.node_name}"

    def token(self) -> str:
        """The token's key expression (``Entity``'s constructor)."""
        parts = [ADMIN_SPACE, str(self.domain_id), self.zid, self.node_id, self.entity_id, self.kind,
                 mangle(self.enclave), mangle(self.namespace), mangle(self.node_name)]
        if self.kind != NODE:
            parts += [mangle(self.topic or ""), mangle(self.type_name or ""), mangle(self.type_hash or ""),
                      (self.qos or _DEFAULT_QOS).encode()]
        return "/".join(parts)


def parse_token(key: str) -> GraphEntity:
    """A liveliness token -> :class:`GraphEntity`; :class:`RmwZenohError` (``bad_token``) where rmw_zenoh rejects it."""
    parts = str(key).split("/")
    if len(parts) < 9 or any(p == "" for p in parts):
        raise RmwZenohError("bad_token", f"liveliness token {key!r}: {len(parts)} chunks or an empty one")
    if parts[0] != ADMIN_SPACE or parts[5] not in (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT):
        raise RmwZenohError("bad_token", f"liveliness token {key!r}: not {ADMIN_SPACE}/<domain>/.../<NN|MP|MS|SS|SC>")
    if not parts[1].isdigit():
        raise RmwZenohError("bad_token", f"liveliness token {key!r}: domain {parts[1]!r} is not a number")
    names = dict(domain_id=int(parts[1]), zid=parts[2], node_id=parts[3], entity_id=parts[4], kind=parts[5],
                 enclave=demangle(parts[6]), namespace=demangle(parts[7]), node_name=demangle(parts[8]))
    if parts[5] == NODE:
        return GraphEntity(**names)
    if len(parts) < 13:
        raise RmwZenohError("bad_token", f"liveliness token {key!r}: an endpoint without topic, type, hash and QoS")
    return GraphEntity(**names, topic=demangle(parts[9]), type_name=demangle(parts[10]),
                       type_hash=demangle(parts[11]), qos=Qos.decode(parts[12]))


# --- attachments ---------------------------------------------------------------------------
_ATTACHMENT = struct.Struct("<qqB16s")
_INT64 = (-2 ** 63, 2 ** 63)


_KEYED = (b"\x0fsequence_number", b"\x10source_timestamp", b"\x0asource_gid")
"""The key strings (LEB128 length + UTF-8) of the attachment of rmw_zenoh Jazzy 0.2.0-0.2.3 and Humble 0.1.0-0.1.1."""
_KEYED_ATTACHMENT = struct.Struct(f"<{len(_KEYED[0])}sq{len(_KEYED[1])}sq{len(_KEYED[2])}sB16s")


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to each sample: ``sequence_number``, ``source_timestamp`` [ns], ``gid`` (16 bytes)."""

    sequence_number: int
    source_timestamp: int
    gid: bytes

    def encode(self, keyed: bool = False) -> bytes:
        """zenoh-ext serialisation of (int64, int64, 16 bytes): 8 + 8 + 1 (length 16, LEB128) + 16 bytes.

        ``keyed``: the older layout (Jazzy 0.2.0-0.2.3, Humble 0.1.0-0.1.1), each value after its name.
        """
        for name in ("sequence_number", "source_timestamp"):
            if not _INT64[0] <= getattr(self, name) < _INT64[1]:
                raise ValueError(f"rmw_zenoh attachment: {name} {getattr(self, name)} is not an int64")
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"rmw_zenoh attachment: a GID has {GID_SIZE} bytes, not {len(self.gid)}")
        if keyed:
            return _KEYED_ATTACHMENT.pack(_KEYED[0], self.sequence_number, _KEYED[1], self.source_timestamp,
                                          _KEYED[2], GID_SIZE, bytes(self.gid))
        return _ATTACHMENT.pack(self.sequence_number, self.source_timestamp, GID_SIZE, bytes(self.gid))

    @classmethod
    def decode(cls, data: bytes | bytearray | memoryview) -> "Attachment":
        """Attachment bytes (either layout) -> Attachment; :class:`RmwZenohError` (``bad_attachment``) otherwise."""
        data = bytes(data)
        if data.startswith(_KEYED[0]) and len(data) >= _KEYED_ATTACHMENT.size:
            k0, seq, k1, stamp, k2, n, gid = _KEYED_ATTACHMENT.unpack_from(data)
            if (k1, k2, n) == (_KEYED[1], _KEYED[2], GID_SIZE):
                return cls(seq, stamp, gid)
        elif len(data) >= _ATTACHMENT.size and data[16] == GID_SIZE:
            seq, stamp, _, gid = _ATTACHMENT.unpack_from(data)
            return cls(seq, stamp, gid)
        raise RmwZenohError("bad_attachment", f"attachment of {len(data)} bytes is not "
                                              f"(int64, int64, {GID_SIZE}-byte GID): {data[:40].hex()}")


def gid_of(token: str) -> bytes:
    """A stable 16-byte GID for the entity behind ``token`` (see the module docstring)."""
    return hashlib.sha256(token.encode()).digest()[:GID_SIZE]


# --- geometry_msgs/PoseStamped (goal poses from RViz / Nav2 tools) --------------------------
@dataclass(frozen=True)
class PlanarPose:
    """A PoseStamped seen from above: position (x, y) [m] and yaw [rad] in ``frame_id`` at ``stamp`` [s]."""

    stamp: float
    frame_id: str
    x: float
    y: float
    yaw: float


def encode_pose_stamped(stamp: float, x: float, y: float, yaw: float, frame_id: str = "map") -> bytes:
    T = _CDR_TYPES.types
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                       orientation=yaw_quaternion(yaw))
    header = T["std_msgs/msg/Header"](stamp=ros_time(stamp), frame_id=frame_id)
    return serialize(T[POSE_STAMPED](header=header, pose=pose), POSE_STAMPED)


def decode_pose_stamped(data: bytes) -> PlanarPose:
    """``geometry_msgs/PoseStamped`` CDR -> PlanarPose; :class:`CdrError` for non-finite values or a bad stamp."""
    m = deserialize(data, POSE_STAMPED)
    p, q, t = m.pose.position, m.pose.orientation, m.header.stamp
    if not all(math.isfinite(v) for v in (p.x, p.y, p.z, q.x, q.y, q.z, q.w)):
        raise CdrError("bad_value", "pose is not finite")
    if not 0 <= t.nanosec < 1_000_000_000:
        raise CdrError("bad_value", f"stamp nanosec {t.nanosec} out of range")
    return PlanarPose(stamp=t.sec + t.nanosec * 1e-9, frame_id=m.header.frame_id, x=float(p.x), y=float(p.y),
                      yaw=quaternion_yaw(q))


# --- a node on an open session -------------------------------------------------------------
@dataclass(frozen=True)
class NodeConfig:
    """Our ROS 2 node as rmw_zenoh peers see it."""

    name: str = "stack_agent"
    """Node name (``ros2 node list`` shows ``<namespace>/<name>``)."""
    namespace: str = "/"
    """The node's namespace, e.g. ``/robot2``; relative topic names resolve in it."""
    domain_id: int = 0
    """ROS_DOMAIN_ID of the robot (0..232); keys and tokens of other domains never meet."""
    distro: str = "jazzy"
    """``jazzy`` (RIHS01 type hashes) or ``humble`` (``TypeHashNotSupported``)."""
    enclave: str = "/"
    """The SROS 2 enclave (``/`` without security)."""

    def __post_init__(self):
        if not (isinstance(self.name, str) and NAME.fullmatch(self.name)):
            raise ValueError(f"rmw_zenoh node: name {self.name!r} is not a ROS 2 node name (letters, digits, '_')")
        for what in ("namespace", "enclave"):
            if not (isinstance(getattr(self, what), str) and _NAMESPACE.fullmatch(getattr(self, what))):
                raise ValueError(f"rmw_zenoh node: {what} {getattr(self, what)!r} is not '/' or '/name[/name...]'")
        if not (isinstance(self.domain_id, int) and not isinstance(self.domain_id, bool)
                and 0 <= self.domain_id <= 232):
            raise ValueError(f"rmw_zenoh node: domain_id {self.domain_id!r} is not an integer 0..232")
        if self.distro not in DISTROS:
            raise ValueError(f"rmw_zenoh node: distro {self.distro!r} is not one of {', '.join(DISTROS)}")


_ENTITY_IDS: dict[str, itertools.count] = {}
_ENTITY_IDS_LOCK = threading.Lock()


def _next_entity_id(zid: str) -> int:
    """rmw_zenoh numbers nodes and endpoints with one counter per session (``get_next_entity_id``)."""
    with _ENTITY_IDS_LOCK:
        return next(_ENTITY_IDS.setdefault(zid, itertools.count()))


class RmwPublisher:
    """A publisher whose samples carry rmw_zenoh's attachment (sequence from 1, wall-clock ns, our GID)."""

    def __init__(self, session: zenoh.Session, key: str, entity: GraphEntity, block: bool | None = None):
        """``block``: wait when the link is congested rather than drop; None: as rmw_zenoh (only for KEEP_ALL).
        Local only: it changes nothing on the wire."""
        qos = entity.qos or DEFAULT_QOS
        block = qos.history == KEEP_ALL if block is None else block
        self.key, self.entity = key, entity
        self.gid = gid_of(entity.token())
        self._lock = threading.Lock()
        self._seq = 1
        self._pub = session.declare_publisher(
            key, encoding=zenoh.Encoding.APPLICATION_CDR,
            reliability=zenoh.Reliability.RELIABLE if qos.reliability == RELIABLE else zenoh.Reliability.BEST_EFFORT,
            congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP)
        self._token = session.liveliness().declare_token(entity.token())

    def put(self, payload: bytes) -> Attachment:
        """Publish CDR bytes; returns the attachment sent with them."""
        with self._lock:
            att = Attachment(self._seq, time.time_ns(), self.gid)
            self._seq += 1
            self._pub.put(payload, attachment=att.encode())
        return att

    def undeclare(self) -> None:
        self._token.undeclare()
        self._pub.undeclare()


class RmwZenohNode:
    """Our node in a ROS 2 graph on rmw_zenoh: its token, publishers that attach, subscribers that check.

    ``session``: an open Zenoh session (the agent's; the node never opens one). ``counters``
    counts what subscriptions drop (``no_attachment``, ``bad_attachment``, ``type_mismatch``,
    ``hash_mismatch``) and ``lost`` (gaps in a publisher's sequence numbers); ``on_malformed``
    is told each counter name as it counts.
    """

    def __init__(self, session: zenoh.Session, config: NodeConfig | None = None, *,
                 on_malformed: Callable[[str], None] | None = None):
        self.config = config or NodeConfig()
        self._session = session
        self._on_malformed = on_malformed or (lambda kind: None)
        self.zid = str(session.info.zid())
        self.counters: dict[str, int] = {}
        self._lock = threading.Lock()
        self._last_seq: dict[bytes, int] = {}
        self._warned: set[str] = set()
        nid = str(_next_entity_id(self.zid))
        cfg = self.config
        self.entity = GraphEntity(cfg.domain_id, self.zid, nid, nid, NODE, cfg.enclave, cfg.namespace, cfg.name)
        self._declared: list = [session.liveliness().declare_token(self.entity.token())]

    @property
    def fq_name(self) -> str:
        return self.entity.node

    def _endpoint(self, kind: str, topic: str, ros_type: str, qos: Qos) -> tuple[str, GraphEntity]:
        cfg = self.config
        fq = fully_qualified(cfg.namespace, topic)
        entity = GraphEntity(cfg.domain_id, self.zid, self.entity.node_id, str(_next_entity_id(self.zid)), kind,
                             cfg.enclave, cfg.namespace, cfg.name, topic=fq, type_name=dds_type_name(ros_type),
                             type_hash=type_hash(ros_type, cfg.distro), qos=qos)
        return topic_key(cfg.domain_id, fq, ros_type, cfg.distro), entity

    def publisher(self, topic: str, ros_type: str, qos: Qos = DEFAULT_QOS, *, block: bool | None = None) -> RmwPublisher:
        """A publisher on ``topic`` (relative to the namespace) with its ``MP`` token (``block``: RmwPublisher's)."""
        key, entity = self._endpoint(PUBLISHER, topic, ros_type, qos)
        pub = RmwPublisher(self._session, key, entity, block)
        self._declared.append(pub)
        return pub

    def subscribe(self, topic: str, ros_type: str, callback: Callable[[bytes, Attachment], None],
                  qos: Qos = DEFAULT_QOS) -> GraphEntity:
        """Subscribe to ``topic`` with its ``MS`` token; ``callback(payload, attachment)`` for each valid sample.

        The subscriber listens on every type and hash of the topic, so that a publisher with another
        definition (a Humble robot for a Jazzy config, a changed message) is counted, not just silent.
        """
        key, entity = self._endpoint(SUBSCRIPTION, topic, ros_type, qos)
        prefix = key.rsplit("/", 2)[0]

        def on_sample(sample: zenoh.Sample) -> None:
            att = self._check(sample, key)
            if att is not None:
                callback(sample.payload.to_bytes(), att)

        self._declared.append(self._session.declare_subscriber(f"{prefix}/*/*", on_sample))
        self._declared.append(self._session.liveliness().declare_token(entity.token()))
        return entity

    def _check(self, sample: zenoh.Sample, key: str) -> Attachment | None:
        """The sample's attachment where the sample is one rmw_zenoh would deliver; None (counted) where not."""
        got = str(sample.key_expr)
        if got != key:
            kind = "type_mismatch" if got.rsplit("/", 2)[1] != key.rsplit("/", 2)[1] else "hash_mismatch"
            self._count(kind, f"{got} is not {key} (another message definition or ROS distro?)")
            return None
        if sample.attachment is None:
            self._count("no_attachment", f"{got}: a sample without attachment (not from rmw_zenoh?)")
            return None
        try:
            att = Attachment.decode(sample.attachment.to_bytes())
        except RmwZenohError as e:
            self._count(e.kind, f"{got}: {e}")
            return None
        with self._lock:
            last = self._last_seq.get(att.gid)
            self._last_seq[att.gid] = att.sequence_number
        gap = 0 if last is None else abs(att.sequence_number - last) - 1
        if gap > 0:
            self._count("lost", f"{got}: {gap} samples lost", gap)
        return att

    def _count(self, kind: str, what: str, n: int = 1) -> None:
        with self._lock:
            self.counters[kind] = self.counters.get(kind, 0) + n
            first = kind not in self._warned
            self._warned.add(kind)
        if first:
            log.warning("rmw_zenoh node %s: %s", self.fq_name, what)
        self._on_malformed(kind)

    def close(self) -> None:
        """Undeclare every endpoint and token (the node leaves the graph)."""
        while self._declared:
            self._declared.pop().undeclare()

    undeclare = close  # so that a node sits with the publishers and subscribers a component undeclares


class RosGraph:
    """The ROS graph as rmw_zenoh's graph cache sees it: liveliness tokens of one domain, parsed.

    Tokens that do not parse are counted in ``counters['bad_token']`` (and told to ``on_malformed``).
    """

    def __init__(self, session: zenoh.Session, domain_id: int = 0, *,
                 on_malformed: Callable[[str], None] | None = None):
        self.counters: dict[str, int] = {}
        self._on_malformed = on_malformed or (lambda kind: None)
        self._lock = threading.Lock()
        self._entities: dict[str, GraphEntity] = {}
        self._sub = session.liveliness().declare_subscriber(f"{ADMIN_SPACE}/{domain_id}/**", self._on_token,
                                                            history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if sample.kind == zenoh.SampleKind.DELETE:
            with self._lock:
                self._entities.pop(key, None)
            return
        try:
            entity = parse_token(key)
        except RmwZenohError as e:
            with self._lock:
                self.counters[e.kind] = self.counters.get(e.kind, 0) + 1
            log.debug("ros graph: %s", e)
            self._on_malformed(e.kind)
            return
        with self._lock:
            self._entities[key] = entity

    def entities(self) -> list[GraphEntity]:
        with self._lock:
            return list(self._entities.values())

    def nodes(self) -> set[str]:
        """Fully qualified node names (``ros2 node list``)."""
        return {e.node for e in self.entities() if e.kind == NODE}

    def endpoints(self, topic: str, kind: str | None = None) -> list[GraphEntity]:
        """Publishers (``MP``) and subscriptions (``MS``) of a fully qualified topic (``ros2 topic info``)."""
        return [e for e in self.entities() if e.topic == topic and (kind is None or e.kind == kind)]

    def close(self) -> None:
        self._sub.undeclare()


__all__ = ["ADMIN_SPACE", "Attachment", "BEST_EFFORT", "CLIENT", "DEFAULT_QOS", "DISTROS", "GID_SIZE", "GraphEntity",
           "HASH_NOT_SUPPORTED", "NAME", "NODE", "NodeConfig", "POSE_STAMPED", "PUBLISHER", "PlanarPose", "Qos", "RELIABLE",
           "RmwPublisher", "RmwZenohError", "RmwZenohNode", "RosGraph", "SENSOR_QOS", "SERVICE", "SUBSCRIPTION",
           "dds_type_name", "decode_pose_stamped", "demangle", "encode_pose_stamped", "fully_qualified", "gid_of",
           "mangle", "parse_token", "rihs01", "topic_key", "type_description", "type_hash"]
