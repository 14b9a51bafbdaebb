"""rmw_zenoh's wire conventions (stack.drivers.rmw_zenoh), checked against code and values we did not write.

- type hashes: the values ROS 2 Jazzy's message packages carry (constants below, with their sources),
  rosbags' own RIHS01 implementation for every type of its Jazzy store, and zenoh-ros2-sdk's hash of .msg text;
- keys, liveliness tokens, QoS strings and attachments: zenoh-ros2-sdk's pure-Python modules (loaded without
  its package ``__init__``, which would pull in its session and repository-fetching code), zenoh-ext's own
  serialiser, and the examples of rmw_zenoh's docs/design.md;
- on loopback: a fake rmw_zenoh robot (built from zenoh-ros2-sdk's key and token builders, dropping samples
  without a valid attachment as rmw_zenoh_cpp does) and our node: odometry in, commands out, the graph seen;
- deploy/zenoh/robot-rmw-zenoh.json5 on a live router: what the agent may and may not touch.
"""

from __future__ import annotations

import importlib
import importlib.util
import itertools
import random
import sys
import time
import types
from pathlib import Path

import pytest
import zenoh
import zenoh.ext as zext
from rosbags.typesys import Stores, get_typestore

from conftest import ROOT, wait_for
from stack.comm import tls
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session
from stack.drivers import rmw_zenoh as rz
from stack.drivers.ros2cdr import LASER_SCAN, ODOMETRY, TWIST, TYPESTORE, CdrError, decode_odometry, decode_twist
from stack.drivers.ros2cdr import encode_laserscan, encode_odometry, encode_twist

# RIHS01 hashes of ROS 2 Jazzy's message packages, as Jazzy itself reports them:
JAZZY_HASHES = {
    # `ros2 topic info /turtle1/cmd_vel --verbose` on Jazzy (the ROS 2 docs' "Understanding topics" tutorial);
    # also rmw_zenoh users' keys, e.g. 0/turtle1/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45...
    "geometry_msgs/msg/Twist": "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
    # ros2/rmw_zenoh docs/design.md, the key of demo_nodes_cpp's `chatter`
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    # golden tables of Jazzy type-support hashes in independent rmw_zenoh-compatible projects (C++, Rust, Go,
    # nano-ros-style CTYPE tables), each read off a Jazzy install (`ros2 topic info -v`, rosidl's generated
    # <pkg>/msg/<Name>.json type descriptions)
    "nav_msgs/msg/Odometry": "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "sensor_msgs/msg/LaserScan": "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828",
    "geometry_msgs/msg/PoseStamped": "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "std_msgs/msg/Header": "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "geometry_msgs/msg/Vector3": "RIHS01_cc12fe83e4c02719f1ce8070bfd14aecd40f75a96696a67a2a1f37f7dbb0765d",
    "geometry_msgs/msg/Pose": "RIHS01_d501954e9476cea2996984e812054b68026ae0bfae789d9a10b23daf35cc90fa",
    "geometry_msgs/msg/Quaternion": "RIHS01_8a765f66778c8ff7c8ab94afcc590a2ed5325a1d9a076ffff38fbce36f458684",
    "geometry_msgs/msg/Point": "RIHS01_6963084842a9b04494d6b2941d11444708d892da2f4b09843b9c43f42a7f6881",
    "geometry_msgs/msg/PoseWithCovariance": "RIHS01_9a7c0fd234b7f45c6098745ecccd773ca1085670e64107135397aee31c02e1bb",
    "geometry_msgs/msg/TwistWithCovariance": "RIHS01_49f574f033f095d8b6cd1beaca5ca7925e296e84af1716d16c89d38b059c8c18",
    "builtin_interfaces/msg/Time": "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",
}

# docs/design.md of ros2/rmw_zenoh: tokens of demo_nodes_cpp's talker and listener
DESIGN_TOKENS = [
    "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener",
    "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,",
    "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,",
]


def sdk(module: str):
    """A pure-Python module of zenoh-ros2-sdk, imported without running the package's ``__init__``."""
    if "zenoh_ros2_sdk" not in sys.modules:
        spec = importlib.util.find_spec("zenoh_ros2_sdk")
        assert spec is not None, "zenoh-ros2-sdk is a test dependency (pip install zenoh-ros2-sdk)"
        pkg = types.ModuleType("zenoh_ros2_sdk")
        pkg.__path__ = list(spec.submodule_search_locations)
        sys.modules["zenoh_ros2_sdk"] = pkg
    return importlib.import_module(f"zenoh_ros2_sdk.{module}")


def sdk_qos(depth: int, best_effort: bool = False) -> str:
    q = sdk("qos")
    rel = q.QosReliability.BEST_EFFORT if best_effort else q.QosReliability.RELIABLE
    return q.QosProfile(reliability=rel, history_depth=depth).encode(default=q.QosProfile(history_depth=42))


# --- type hashes -----------------------------------------------------------------------------
@pytest.mark.parametrize("typename", sorted(JAZZY_HASHES))
def test_type_hashes_are_jazzys(typename):
    assert rz.rihs01(typename) == JAZZY_HASHES[typename]
    assert rz.type_hash(typename, "jazzy") == JAZZY_HASHES[typename]


def test_type_hashes_agree_with_rosbags_for_every_jazzy_type():
    store = get_typestore(Stores.ROS2_JAZZY)
    wrong = [t for t in store.fielddefs if rz.rihs01(t) != store.hash_rihs01(t)]
    assert not wrong and len(store.fielddefs) > 100


def test_type_hash_agrees_with_zenoh_ros2_sdk_from_msg_text():
    utils = sdk("utils")
    vector3 = "float64 x\nfloat64 y\nfloat64 z\n"
    h = utils.compute_type_hash_from_msg(TWIST, "Vector3 linear\nVector3 angular\n",
                                         {"geometry_msgs/msg/Vector3": vector3})
    assert h == rz.rihs01(TWIST)


def test_type_description_names_nested_types_sorted():
    desc = rz.type_description(ODOMETRY)
    names = [d["type_name"] for d in desc["referenced_type_descriptions"]]
    assert names == sorted(names) and "std_msgs/msg/Header" in names and "builtin_interfaces/msg/Time" in names
    assert desc["type_description"]["fields"][1] == {
        "name": "child_frame_id", "type": {"type_id": 17, "capacity": 0, "string_capacity": 0, "nested_type_name": ""}}
    cov = desc["referenced_type_descriptions"][names.index("geometry_msgs/msg/PoseWithCovariance")]["fields"][1]
    assert cov["type"]["type_id"] == 11 + 48 and cov["type"]["capacity"] == 36  # float64[36]: FIELD_TYPE_DOUBLE_ARRAY


def test_humble_has_no_type_hash():
    assert rz.type_hash(TWIST, "humble") == "TypeHashNotSupported"
    assert rz.topic_key(0, "/robot2/cmd_vel", TWIST, "humble") == \
        "0/robot2/cmd_vel/geometry_msgs::msg::dds_::Twist_/TypeHashNotSupported"


@pytest.mark.parametrize("call, match", [
    (lambda: rz.type_hash(TWIST, "iron"), "ros_distro 'iron'"),
    (lambda: rz.type_hash("geometry_msgs/Twist"), "not a message type"),
    (lambda: rz.rihs01("nope_msgs/msg/Nope"), "no message definition"),
    (lambda: rz.fully_qualified("/robot2", "cmd vel"), "not a ROS 2 topic name"),
])
def test_bad_names_are_one_line_errors(call, match):
    with pytest.raises(ValueError, match=match) as e:
        call()
    assert "\n" not in str(e.value)


# --- keys, tokens, QoS ------------------------------------------------------------------------
@pytest.mark.parametrize("ns, topic, typename", [
    ("/robot2", "cmd_vel", TWIST), ("/robot2", "platform/odom/filtered", ODOMETRY),
    ("/", "scan", LASER_SCAN), ("/j100_0421", "/goal_pose", rz.POSE_STAMPED)])
def test_data_keys_match_zenoh_ros2_sdk(ns, topic, typename):
    fq = rz.fully_qualified(ns, topic)
    theirs = sdk("keyexpr").topic_keyexpr(3, fq, sdk("utils").ros2_to_dds_type(typename), JAZZY_HASHES[typename])
    assert rz.topic_key(3, fq, typename) == theirs
    assert rz.dds_type_name(typename) == sdk("utils").ros2_to_dds_type(typename)


def test_node_and_endpoint_tokens_match_zenoh_ros2_sdk():
    entity, keyexpr = sdk("entity"), sdk("keyexpr")
    zid = "8b20917502ee955ac4476e0266340d5c"
    node = entity.NodeEntity(domain_id=0, session_id=zid, node_id=4, node_name="stack_agent", namespace="/robot2")
    ours = rz.GraphEntity(0, zid, "4", "4", rz.NODE, "/", "/robot2", "stack_agent")
    assert ours.token() == keyexpr.node_liveliness_keyexpr(node)
    for kind, topic, typename, qos, theirs_qos in [
            (rz.PUBLISHER, "/robot2/cmd_vel", TWIST, rz.DEFAULT_QOS, sdk_qos(10)),
            (rz.SUBSCRIPTION, "/robot2/sensors/lidar2d_0/scan", LASER_SCAN, rz.SENSOR_QOS, sdk_qos(5, True))]:
        ep = entity.EndpointEntity(node=node, entity_id=7, kind=entity.EntityKind(kind), name=topic,
                                   dds_type_name=rz.dds_type_name(typename), type_hash=JAZZY_HASHES[typename],
                                   qos=theirs_qos)
        mine = rz.GraphEntity(0, zid, "4", "7", kind, "/", "/robot2", "stack_agent", topic=topic,
                              type_name=rz.dds_type_name(typename), type_hash=rz.rihs01(typename), qos=qos)
        assert mine.token() == keyexpr.endpoint_liveliness_keyexpr(ep)
        assert rz.parse_token(mine.token()) == mine


@pytest.mark.parametrize("token", DESIGN_TOKENS)
def test_rmw_zenoh_design_tokens_parse_and_round_trip(token):
    e = rz.parse_token(token)
    assert e.token() == token
    assert e.node in ("/listener", "/talker")
    if e.kind != rz.NODE:
        assert e.topic == "/chatter" and e.type_name == "std_msgs::msg::dds_::String_"
        assert e.qos.depth in (7, 10) and e.qos.reliability == rz.RELIABLE and e.qos.deadline == rz.INFINITE


def test_qos_strings_round_trip_against_zenoh_ros2_sdk():
    q = sdk("qos")
    for ours, depth, best_effort in [(rz.DEFAULT_QOS, 10, False), (rz.SENSOR_QOS, 5, True), (rz.Qos(depth=3), 3, False)]:
        assert ours.encode() == sdk_qos(depth, best_effort)
        assert rz.Qos.decode(ours.encode()) == ours
    odd = rz.Qos(durability=rz.TRANSIENT_LOCAL, history=rz.KEEP_ALL, deadline=(1, 5), liveliness=rz.MANUAL_BY_TOPIC,
                 liveliness_lease=(2, 0))
    theirs = q.QosProfile.decode(odd.encode())
    assert rz.Qos.decode(odd.encode()) == odd
    assert theirs.durability == q.QosDurability.TRANSIENT_LOCAL and theirs.deadline == q.Duration(1, 5)


@pytest.mark.parametrize("text", ["", "::,10:,:,:,", "::10:,:,:,,", "9::,10:,:,:,,", "::,-1:,:,:,,", "::,x:,:,:,,",
                                  ":::,10:,:,:,", "::,10:,:,:2,,"])
def test_bad_qos_strings_are_counted_errors(text):
    with pytest.raises(rz.RmwZenohError) as e:
        rz.Qos.decode(text)
    assert e.value.kind == "bad_qos"


@pytest.mark.parametrize("token", [
    "@ros2_lv/0/z/0/0/NN/%/%", "@ros2_lv/0/z/0/0/XX/%/%/n", "ros2_lv/0/z/0/0/NN/%/%/n", "@ros2_lv/x/z/0/0/NN/%/%/n",
    "@ros2_lv/0/z/0/0/NN//%/n", "@ros2_lv/0/z/0/1/MP/%/%/n/%t/T_", "@ros2_lv/0/z/0/1/MP/%/%/n/%t/T_/H/notqos"])
def test_malformed_tokens_are_counted_errors(token):
    with pytest.raises(rz.RmwZenohError) as e:
        rz.parse_token(token)
    assert e.value.kind in ("bad_token", "bad_qos")


def test_token_parser_never_raises_anything_else():
    rnd = random.Random(7)
    alphabet = "@ros2_lv/0123456789NMPSC%:,abc"
    for base in DESIGN_TOKENS:
        for _ in range(300):
            chars = list(base)
            for _ in range(rnd.randint(1, 4)):
                chars[rnd.randrange(len(chars))] = rnd.choice(alphabet)
            try:
                rz.parse_token("".join(chars))
            except rz.RmwZenohError:
                pass


# --- attachments ------------------------------------------------------------------------------
def test_attachment_is_what_zenoh_ext_serialises():
    gid = bytes(range(1, 17))
    att = rz.Attachment(42, 1_733_000_000_123_456_789, gid)
    ref = zext.z_serialize((zext.Int64(42), zext.Int64(1_733_000_000_123_456_789), gid)).to_bytes()
    assert att.encode() == ref and len(ref) == 33
    back = zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], zenoh.ZBytes(att.encode()))
    assert back == (42, att.source_timestamp, gid)
    assert rz.Attachment.decode(ref) == att
    negative = rz.Attachment(-1, -5, gid)
    assert negative.encode() == zext.z_serialize((zext.Int64(-1), zext.Int64(-5), gid)).to_bytes()


def test_older_keyed_attachments_are_what_zenoh_ext_serialises():
    """rmw_zenoh Jazzy 0.2.0-0.2.3 / Humble 0.1.0-0.1.1: serialize("sequence_number"), int64, ... (string keys)."""
    gid = bytes(range(16))
    ref = zext.z_serialize(("sequence_number", zext.Int64(3), "source_timestamp", zext.Int64(99),
                            "source_gid", gid)).to_bytes()
    att = rz.Attachment(3, 99, gid)
    assert att.encode(keyed=True) == ref and rz.Attachment.decode(ref) == att
    for broken in (ref[:-1], ref.replace(b"source_gid", b"source_gix"), ref[:-17] + b"\x0f" + gid[:15]):
        with pytest.raises(rz.RmwZenohError):
            rz.Attachment.decode(broken)


def test_attachment_agrees_with_zenoh_ros2_sdk():
    Att = sdk("attachment").Attachment
    gid = bytes(range(100, 116))
    theirs = Att(sequence_id=7, timestamp_ns=123456789, gid=gid)
    assert rz.Attachment(7, 123456789, gid).encode() == theirs.to_bytes()
    back = Att.from_bytes(rz.Attachment(9, 5, gid).encode())
    assert (back.sequence_id, back.timestamp_ns, back.gid) == (9, 5, gid)


@pytest.mark.parametrize("data", [b"", b"\x01\x02", bytes(32), bytes(16) + b"\x18" + bytes(24),
                                  zext.z_serialize(("sequence_number", zext.Int64(1))).to_bytes()])
def test_malformed_attachments_are_counted_errors(data):
    with pytest.raises(rz.RmwZenohError) as e:
        rz.Attachment.decode(data)
    assert e.value.kind == "bad_attachment" and "\n" not in str(e.value)


def test_gid_is_stable_and_per_entity():
    a, b = (rz.parse_token(t).token() for t in DESIGN_TOKENS[1:])
    assert rz.gid_of(a) == rz.gid_of(a) and rz.gid_of(a) != rz.gid_of(b) and len(rz.gid_of(a)) == 16


# --- PoseStamped ------------------------------------------------------------------------------
def test_pose_stamped_round_trips_against_rosbags():
    data = rz.encode_pose_stamped(12.25, 3.0, -1.5, 0.75, frame_id="map")
    m = TYPESTORE.deserialize_cdr(data, rz.POSE_STAMPED)
    assert (m.header.frame_id, m.header.stamp.sec, m.header.stamp.nanosec) == ("map", 12, 250_000_000)
    p = rz.decode_pose_stamped(data)
    assert (p.frame_id, p.x, p.y) == ("map", 3.0, -1.5) and p.yaw == pytest.approx(0.75) and p.stamp == 12.25
    with pytest.raises(CdrError):
        rz.decode_pose_stamped(encode_twist(1.0, 0.0))
    with pytest.raises(CdrError):
        rz.decode_pose_stamped(rz.encode_pose_stamped(0.0, float("nan"), 0.0, 0.0))


@pytest.mark.parametrize("kw, match", [({"name": "stack-agent"}, "name"), ({"namespace": "robot2"}, "namespace"),
                                       ({"domain_id": 233}, "domain_id"), ({"domain_id": True}, "domain_id"),
                                       ({"distro": "iron"}, "distro"), ({"enclave": "/a/"}, "enclave")])
def test_node_config_errors_are_one_line(kw, match):
    with pytest.raises(ValueError, match=match) as e:
        rz.NodeConfig(**kw)
    assert "\n" not in str(e.value)


# --- on loopback: a fake rmw_zenoh robot and our node ------------------------------------------
_domains = itertools.count(10)


@pytest.fixture(scope="module")
def sessions():
    ep = free_tcp_endpoint()
    with open_session(SessionConfig(mode="router", listen=[ep])), \
            open_session(SessionConfig(connect=[ep])) as s_agent, \
            open_session(SessionConfig(connect=[ep])) as s_robot:
        yield s_agent, s_robot


class FakeRmwRobot:
    """A Jazzy Jackal as rmw_zenoh_cpp shows it, from zenoh-ros2-sdk's builders and zenoh-ext's deserialiser.

    Its node ``/robot2/jackal`` publishes odometry (with attachments) and subscribes to ``cmd_vel``,
    dropping samples without an attachment that deserialises as (int64, int64, 16 bytes), as
    rmw_zenoh_cpp's subscription does.
    """

    def __init__(self, session: zenoh.Session, domain: int, ns: str = "/robot2"):
        entity, keyexpr, utils = sdk("entity"), sdk("keyexpr"), sdk("utils")
        self.session, self.domain = session, domain
        zid = str(session.info.zid())
        node = entity.NodeEntity(domain_id=domain, session_id=zid, node_id=0, node_name="jackal", namespace=ns)
        self.odom_fq, self.cmd_fq = f"{ns}/platform/odom/filtered", f"{ns}/cmd_vel"
        eps = [(1, "MP", self.odom_fq, ODOMETRY), (2, "MS", self.cmd_fq, TWIST)]
        self.tokens = [keyexpr.node_liveliness_keyexpr(node)] + [
            keyexpr.endpoint_liveliness_keyexpr(entity.EndpointEntity(
                node=node, entity_id=i, kind=entity.EntityKind(k), name=fq, dds_type_name=utils.ros2_to_dds_type(t),
                type_hash=JAZZY_HASHES[t], qos=sdk_qos(10))) for i, k, fq, t in eps]
        self.odom_key = keyexpr.topic_keyexpr(domain, self.odom_fq, utils.ros2_to_dds_type(ODOMETRY),
                                              JAZZY_HASHES[ODOMETRY])
        self.cmd_key = keyexpr.topic_keyexpr(domain, self.cmd_fq, utils.ros2_to_dds_type(TWIST), JAZZY_HASHES[TWIST])
        self.gid = bytes(range(200, 216))
        self.seq = 0
        self.accepted: list = []  # (sequence, timestamp, gid, (v, w))
        self.dropped: dict[str, int] = {}
        self._declared = [session.liveliness().declare_token(t) for t in self.tokens]
        self._declared.append(session.declare_subscriber(self.cmd_key, self._on_cmd))

    def _on_cmd(self, sample: zenoh.Sample) -> None:
        if sample.attachment is None:
            self.dropped["no_attachment"] = self.dropped.get("no_attachment", 0) + 1
            return
        try:
            seq, stamp, gid = zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], sample.attachment)
        except zext.ZDeserializeError:
            self.dropped["bad_attachment"] = self.dropped.get("bad_attachment", 0) + 1
            return
        assert len(gid) == 16
        self.accepted.append((seq, stamp, gid, decode_twist(sample.payload.to_bytes())))

    def publish_odom(self, x: float, attachment: bool = True, key: str | None = None, seq_step: int = 1) -> None:
        self.seq += seq_step
        att = sdk("attachment").Attachment(sequence_id=self.seq, timestamp_ns=time.time_ns(), gid=self.gid).to_bytes()
        self.session.put(key or self.odom_key, encode_odometry(time.time(), x, 0.5, 0.1, 0.2, 0.0),
                         attachment=att if attachment else None)

    def close(self) -> None:
        for d in self._declared:
            d.undeclare()


def test_node_talks_to_a_fake_rmw_zenoh_robot(sessions):
    s_agent, s_robot = sessions
    domain = next(_domains)
    robot = FakeRmwRobot(s_robot, domain)
    node = rz.RmwZenohNode(s_agent, rz.NodeConfig(name="stack_agent", namespace="/robot2", domain_id=domain))
    graph = rz.RosGraph(s_robot, domain)
    odoms = []
    try:
        node.subscribe("platform/odom/filtered", ODOMETRY, lambda p, a: odoms.append((decode_odometry(p), a)))
        node.subscribe("sensors/lidar2d_0/scan", LASER_SCAN, lambda p, a: None, qos=rz.SENSOR_QOS)
        cmd = node.publisher("cmd_vel", TWIST)
        assert cmd.key == robot.cmd_key
        # odometry in
        assert wait_for(lambda: robot.publish_odom(1.25) or odoms, 3.0), "no odometry reached the node"
        odom, att = odoms[-1]
        assert odom.pose[0] == pytest.approx(1.25) and att.gid == robot.gid and 1 <= att.sequence_number <= robot.seq
        # commands out, with attachments the robot accepts: sequence from 1, our GID, a wall-clock stamp
        assert wait_for(lambda: cmd.put(encode_twist(0.4, -0.2)) and len(robot.accepted) >= 3, 3.0)
        seqs = [a[0] for a in robot.accepted]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and robot.dropped == {}
        assert {a[2] for a in robot.accepted} == {cmd.gid} and robot.accepted[-1][3] == (0.4, -0.2)
        assert abs(robot.accepted[-1][1] - time.time_ns()) < 5e9
        _graph_shows_our_node(graph, robot, node, domain)
        assert node.counters == {}
    finally:
        node.close()
        graph.close()
        robot.close()


def _graph_shows_our_node(graph: rz.RosGraph, robot: FakeRmwRobot, node: rz.RmwZenohNode, domain: int) -> None:
    """What `ros2 node list` and `ros2 topic info -v` on the robot would read, raw and parsed."""
    entity, keyexpr = sdk("entity"), sdk("keyexpr")
    assert wait_for(lambda: "/robot2/stack_agent" in graph.nodes() and len(graph.entities()) >= 7, 3.0)
    assert graph.nodes() == {"/robot2/stack_agent", "/robot2/jackal"}
    (pub,) = [e for e in graph.endpoints("/robot2/cmd_vel", rz.PUBLISHER)]
    assert (pub.node, pub.type_name, pub.type_hash) == ("/robot2/stack_agent", "geometry_msgs::msg::dds_::Twist_",
                                                        JAZZY_HASHES[TWIST])
    subs = {e.topic: e for e in graph.entities() if e.kind == rz.SUBSCRIPTION and e.node == "/robot2/stack_agent"}
    assert set(subs) == {"/robot2/platform/odom/filtered", "/robot2/sensors/lidar2d_0/scan"}
    assert subs["/robot2/sensors/lidar2d_0/scan"].qos.reliability == rz.BEST_EFFORT
    # the raw tokens, as zenoh-ros2-sdk would have written them for our node
    sdk_node = entity.NodeEntity(domain_id=domain, session_id=node.zid, node_id=int(node.entity.node_id),
                                 node_name="stack_agent", namespace="/robot2")
    want = {keyexpr.node_liveliness_keyexpr(sdk_node)}
    for e in [pub, *subs.values()]:
        want.add(keyexpr.endpoint_liveliness_keyexpr(entity.EndpointEntity(
            node=sdk_node, entity_id=int(e.entity_id), kind=entity.EntityKind(e.kind), name=e.topic,
            dds_type_name=e.type_name, type_hash=e.type_hash,
            qos=sdk_qos(e.qos.depth, e.qos.reliability == rz.BEST_EFFORT))))
    raw: set[str] = set()
    sub = robot.session.liveliness().declare_subscriber(f"@ros2_lv/{domain}/**", lambda t: raw.add(str(t.key_expr)),
                                                        history=True)
    try:
        assert wait_for(lambda: raw == want | set(robot.tokens), 3.0), raw ^ (want | set(robot.tokens))
    finally:
        sub.undeclare()
    assert graph.counters == {}


def test_malformed_samples_and_tokens_are_counted_not_delivered(sessions):
    s_agent, s_robot = sessions
    domain = next(_domains)
    robot = FakeRmwRobot(s_robot, domain)
    seen: list[str] = []
    node = rz.RmwZenohNode(s_agent, rz.NodeConfig(namespace="/robot2", domain_id=domain), on_malformed=seen.append)
    graph = rz.RosGraph(s_agent, domain, on_malformed=seen.append)
    odoms = []
    humble_key = robot.odom_key.rsplit("/", 1)[0] + "/TypeHashNotSupported"
    other_type = f"{domain}/robot2/platform/odom/filtered/nav_msgs::msg::dds_::Path_/{JAZZY_HASHES[ODOMETRY]}"
    bad_tokens = [f"@ros2_lv/{domain}/z/0/0/NN/%/%", f"@ros2_lv/{domain}/z/0/0/XX/%/%/n",
                  f"@ros2_lv/{domain}/z/0/1/MP/%/%/n/%t/T_/H/notqos"]
    declared = [s_robot.liveliness().declare_token(t) for t in bad_tokens]
    try:
        node.subscribe("platform/odom/filtered", ODOMETRY, lambda p, a: odoms.append(a))
        assert wait_for(lambda: robot.publish_odom(0.0) or odoms, 3.0)
        robot.publish_odom(1.0, attachment=False)
        s_robot.put(robot.odom_key, encode_odometry(0.0, 0, 0, 0, 0, 0), attachment=b"\x00\x01junk")
        robot.publish_odom(2.0, key=humble_key)
        robot.publish_odom(2.0, key=other_type)
        robot.publish_odom(3.0, seq_step=4)  # three samples missing from the robot's sequence
        want = {"no_attachment": 1, "bad_attachment": 1, "hash_mismatch": 1, "type_mismatch": 1}
        assert wait_for(lambda: all(node.counters.get(k) == n for k, n in want.items())
                        and "lost" in node.counters, 3.0)
        assert node.counters["lost"] >= 3
        assert wait_for(lambda: graph.counters.get("bad_token", 0) + graph.counters.get("bad_qos", 0) == 3, 3.0)
        assert set(seen) >= {"no_attachment", "bad_attachment", "hash_mismatch", "type_mismatch", "lost", "bad_token"}
        assert wait_for(lambda: odoms[-1].sequence_number == robot.seq, 3.0)
        assert all(a.gid == robot.gid for a in odoms)
        assert graph.nodes() == {"/robot2/jackal", "/robot2/stack_agent"}
    finally:
        for d in declared:
            d.undeclare()
        node.close()
        graph.close()
        robot.close()


def test_closing_the_node_leaves_the_graph(sessions):
    s_agent, s_robot = sessions
    domain = next(_domains)
    graph = rz.RosGraph(s_robot, domain)
    cfg = rz.NodeConfig(name="gone", namespace="/robot7", domain_id=domain, distro="humble")
    node = rz.RmwZenohNode(s_agent, cfg)
    try:
        node.publisher("cmd_vel", TWIST)
        assert wait_for(lambda: graph.endpoints("/robot7/cmd_vel"), 3.0)
        assert graph.endpoints("/robot7/cmd_vel")[0].type_hash == "TypeHashNotSupported"
        node.close()
        assert wait_for(lambda: not graph.entities(), 3.0), graph.entities()
    finally:
        node.close()
        graph.close()


# --- deploy/zenoh/robot-rmw-zenoh.json5 on a live router ----------------------------------------
def _robot_router_config(tmp_path, pki) -> Path:
    """The deploy file with this test's certificates, and without the site router it would mesh with."""
    text = (ROOT / "deploy" / "zenoh" / "robot-rmw-zenoh.json5").read_text()
    text = text.replace("/etc/stack/certs", str(pki)).replace('connect: { endpoints: ["tls/192.0.2.1:7447"] }',
                                                              "connect: { endpoints: [] }")
    assert "endpoints: [] }" in text
    path = tmp_path / "robot-rmw-zenoh.json5"
    path.write_text(text)
    return path


def test_robot_router_config_exposes_only_the_agents_topics(tmp_path):
    pki = tmp_path / "pki"
    tls.make_ca(pki)
    tls.issue(pki, "robot-router", "router.fleet-a.robot-2")
    tls.issue(pki, "agent", "fleet-a.robot-2")
    tls.issue(pki, "stranger", "fleet-a.robot-3")
    conf = _robot_router_config(tmp_path, pki)
    ros_ep, agent_ep = free_tcp_endpoint(), free_tcp_endpoint().replace("tcp/", "tls/")

    def client(name: str) -> SessionConfig:
        cfg = tls.write_config(pki / f"{name}.json5", tls.tls_block(pki / "ca.pem", pki / f"{name}.pem",
                                                                      pki / f"{name}.key"))
        return SessionConfig(connect=[agent_ep], config_file=str(cfg))

    with open_session(SessionConfig(mode="router", listen=[ros_ep, agent_ep], config_file=str(conf))), \
            open_session(SessionConfig(connect=[ros_ep])) as s_robot, \
            open_session(client("agent")) as s_agent, open_session(client("stranger")) as s_stranger:
        robot = FakeRmwRobot(s_robot, 0)
        graph = rz.RosGraph(s_robot, 0)
        node = rz.RmwZenohNode(s_agent, rz.NodeConfig(name="stack_agent", namespace="/robot2"))
        stranger = rz.RmwZenohNode(s_stranger, rz.NodeConfig(name="stranger", namespace="/robot2"))
        odoms, strangers_odoms, secret = [], [], []
        try:
            node.subscribe("platform/odom/filtered", ODOMETRY, lambda p, a: odoms.append(a))
            node.subscribe("secret", rz.POSE_STAMPED, lambda p, a: secret.append(a))
            stranger.subscribe("platform/odom/filtered", ODOMETRY, lambda p, a: strangers_odoms.append(a))
            cmd, other = node.publisher("cmd_vel", TWIST), node.publisher("/robot2/cmd_vel_unsafe", TWIST)
            assert wait_for(lambda: robot.publish_odom(1.0) or odoms, 5.0), "odometry did not reach the agent"
            assert wait_for(lambda: cmd.put(encode_twist(0.1, 0.0)) and robot.accepted, 5.0)
            assert wait_for(lambda: "/robot2/stack_agent" in graph.nodes(), 5.0), graph.nodes()
            # robot.ros_graph's topics (docs/ros2.md): a goal in, the agent's estimate out
            goals, estimates = [], []
            node.subscribe("goal_pose", rz.POSE_STAMPED, lambda p, a: goals.append(a))
            s_robot.declare_subscriber(rz.topic_key(0, "/robot2/formation/odometry", ODOMETRY),
                                       lambda s: estimates.append(s))
            est = node.publisher("formation/odometry", ODOMETRY)
            goal_key = rz.topic_key(0, "/robot2/goal_pose", rz.POSE_STAMPED)
            assert wait_for(lambda: s_robot.put(goal_key, rz.encode_pose_stamped(0.0, 1.0, 2.0, 0.0),
                                                attachment=rz.Attachment(1, 1, robot.gid).encode()) or goals, 5.0)
            assert wait_for(lambda: est.put(encode_odometry(0.0, 1.0, 2.0, 0.0, 0.0, 0.0)) or estimates, 5.0)
            # what the agent may not touch: other ROS topics, either way; and a stranger gets nothing
            unsafe = []
            sub = s_robot.declare_subscriber(other.key, lambda s: unsafe.append(s))
            secret_key = rz.topic_key(0, "/robot2/secret", rz.POSE_STAMPED)
            for _ in range(20):
                other.put(encode_twist(2.0, 0.0))
                s_robot.put(secret_key, rz.encode_pose_stamped(0.0, 1.0, 2.0, 0.0),
                            attachment=rz.Attachment(1, 1, robot.gid).encode())
                robot.publish_odom(2.0)
                time.sleep(0.01)
            time.sleep(0.3)
            sub.undeclare()
            assert unsafe == [] and secret == [] and strangers_odoms == []
            assert "/robot2/stranger" not in graph.nodes()
        finally:
            stranger.close()
            node.close()
            graph.close()
            robot.close()
