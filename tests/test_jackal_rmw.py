"""The ``jackal`` driver on ``transport: rmw_zenoh``: a ROS 2 node on the robot's rmw_zenoh graph.

Against two robots on loopback Zenoh (a router, scouting off): the fake rmw_zenoh Jackal of
tests/test_rmw_zenoh.py (built from zenoh-ros2-sdk's key and token builders and zenoh-ext's
deserialiser: code we did not write), and our simulated Jackal on the same transport, whose
hardware-like settings must give the driver the same samples as on the bridge transport. Last, a
lock-step fleet on ``robot.jackal.transport: rmw_zenoh`` against the same fleet on the bridge.
"""

from __future__ import annotations

import itertools
import math
import time

import pytest

from conftest import lockstep_report, run_fleet, scenario_dict, wait_for, write_scenario
from stack.comm.keys import Keys
from stack.drivers import rmw_zenoh as rz
from stack.drivers.base import DriverError, DriverLimits
from stack.drivers.jackal import JackalConfig, JackalDriver
from stack.drivers.ros2cdr import LASER_SCAN, ODOMETRY, TWIST, decode_twist, encode_odometry, encode_twist
from stack.scenario import LidarConfig, RobotConfig
from stack.sim_bridge.devices import Body, DeviceError
from stack.sim_bridge.jackal_sim import JackalDevice
from test_rmw_zenoh import JAZZY_HASHES, FakeRmwRobot, sessions  # noqa: F401 (sessions: a loopback router, 2 sessions)

WIDE = DriverLimits(v_max=10.0, w_max=10.0, cmd_timeout=5.0)
RMW = {"transport": "rmw_zenoh"}
_ns = itertools.count()
_domains = itertools.count(40)


# --- settings -------------------------------------------------------------------------------
def test_transport_settings_are_checked_in_one_line():
    assert JackalConfig().transport == "bridge" and JackalConfig().key(3, "cmd_vel") == "robot3/cmd_vel"
    assert JackalConfig().topic_key(3, "cmd_vel", TWIST) == "robot3/cmd_vel"  # the bridge's keys, as before
    cfg = JackalConfig(transport="rmw_zenoh", namespace="robot2", domain_id=7)
    assert cfg.topic_key(2, "cmd_vel", TWIST) == f"7/robot2/cmd_vel/geometry_msgs::msg::dds_::Twist_/{JAZZY_HASHES[TWIST]}"
    humble = JackalConfig(transport="rmw_zenoh", ros_distro="humble")
    assert humble.topic_key(4, "platform/odom/filtered", ODOMETRY).endswith("/robot4/platform/odom/filtered/"
                                                                         "nav_msgs::msg::dds_::Odometry_/TypeHashNotSupported")
    assert cfg.node_config(2) == rz.NodeConfig(name="stack_agent", namespace="/robot2", domain_id=7)
    for kw, words in (({"transport": "dds"}, "transport 'dds' is not one of bridge, rmw_zenoh"),
                      ({"domain_id": 233}, "domain_id must be an integer 0..232"),
                      ({"domain_id": True}, "domain_id must be an integer"),
                      ({"ros_distro": "iron"}, "ros_distro 'iron' is not one of jazzy, humble"),
                      ({"node_name": "stack-agent"}, "node_name 'stack-agent' is not a ROS 2 node name"),
                      ({**RMW, "node_name": "9x"}, "transport rmw_zenoh.*name '9x'"),
                      ({**RMW, "namespace": "fleet-a/robot2"}, "transport rmw_zenoh.*namespace '/fleet-a/robot2'"),
                      ({**RMW, "cmd_topic": "cmd-vel"}, "transport rmw_zenoh.*topic 'cmd-vel'")):
        with pytest.raises(ValueError, match=words) as e:
            JackalConfig(**kw)
        assert "\n" not in str(e.value) and str(e.value).startswith("jackal driver")
    JackalConfig(namespace="fleet-a/robot2")  # a bridge's key prefix need not be a ROS name
    with pytest.raises(DeviceError, match="robot 3: jackal driver: transport 'x'"):
        JackalDevice(RobotConfig(id=3, role=None, pose=(0.0, 0.0, 0.0), driver_params={"jackal": {"transport": "x"}}),
                     session=object())


def test_the_simulated_jackals_default_namespace_is_a_ros_namespace_on_rmw_zenoh():
    robot = RobotConfig(id=3, role=None, pose=(0.0, 0.0, 0.0), driver_params={"jackal": dict(RMW)})
    dev = JackalDevice(robot, session=object(), keys=Keys("fleet-a.7"))
    assert dev.namespace == "jackal/fleet_a_7/robot3"
    assert dev.cmd_key == f"0/jackal/fleet_a_7/robot3/cmd_vel/geometry_msgs::msg::dds_::Twist_/{JAZZY_HASHES[TWIST]}"
    bridge = JackalDevice(RobotConfig(id=3, role=None, pose=(0.0, 0.0, 0.0)), session=object(), keys=Keys("fleet-a.7"))
    assert bridge.cmd_key == "jackal/fleet-a.7/robot3/cmd_vel"  # unchanged on the bridge


# --- over Zenoh -----------------------------------------------------------------------------
def test_driver_drives_a_fake_rmw_zenoh_robot(sessions):
    """Code we did not write on the robot's side: its keys and tokens, its attachment check."""
    s_agent, s_robot = sessions
    domain = next(_domains)
    robot = FakeRmwRobot(s_robot, domain, ns="/robot2")
    graph = rz.RosGraph(s_robot, domain)
    malformed: list[str] = []
    drv = JackalDriver(2, WIDE, session=s_agent, transport="rmw_zenoh", domain_id=domain, open_timeout=0.0,
                       on_malformed=malformed.append)
    try:
        drv.open()
        assert drv.cmd_key == robot.cmd_key and drv.odom_key == robot.odom_key
        assert wait_for(lambda: (robot.publish_odom(1.5), time.sleep(0.02), drv.read())[-1], 3.0), drv.counters
        assert drv.read().pose[0] == 1.5 and drv.read().v == 0.2
        assert drv.command(0.4, -0.3) == (0.4, -0.3)
        assert wait_for(lambda: robot.accepted and robot.accepted[-1][3] == (0.4, -0.3)), robot.dropped
        seqs = [a[0] for a in robot.accepted]
        assert robot.dropped == {} and seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        assert {a[2] for a in robot.accepted} == {drv._pub.gid} and abs(robot.accepted[-1][1] - time.time_ns()) < 5e9
        assert wait_for(lambda: "/robot2/stack_agent" in graph.nodes())
        # each entity's token arrives on its own: wait for each, as `ros2 topic info` run a moment later would see it
        assert wait_for(lambda: [e.node for e in graph.endpoints("/robot2/cmd_vel", rz.PUBLISHER)] == ["/robot2/stack_agent"])
        odom = ("/robot2/platform/odom/filtered", rz.SUBSCRIPTION)
        assert wait_for(lambda: [(e.node, e.type_hash) for e in graph.endpoints(*odom)]
                        == [("/robot2/stack_agent", JAZZY_HASHES[ODOMETRY])]), graph.endpoints(*odom)
        scan = ("/robot2/sensors/lidar2d_0/scan", rz.SUBSCRIPTION)
        assert wait_for(lambda: [e.qos for e in graph.endpoints(*scan)] == [rz.SENSOR_QOS]), graph.endpoints(*scan)
        assert drv.fault is None and malformed == []
    finally:
        drv.close()
        robot.close()
    assert wait_for(lambda: "/robot2/stack_agent" not in graph.nodes()), graph.nodes()  # the tokens went with it
    assert wait_for(lambda: graph.endpoints("/robot2/cmd_vel") == []), graph.endpoints("/robot2/cmd_vel")
    graph.close()


class Rig:
    """Our simulated Jackal on rmw_zenoh (the world's session) and a driver for it (the agent's)."""

    def __init__(self, sessions, transport: str = "rmw_zenoh", device=None, **cfg):
        self.s_agent, self.s_world = sessions
        settings = {"transport": transport}
        robot = RobotConfig(id=2, role="follower", pose=(1.0, -2.0, 0.5), driver_params={"jackal": settings},
                            lidar=LidarConfig(beams=180, fov=math.pi, range=5.0))
        device = {"ideal": True} if device is None else device  # the transport is the point: world-frame odometry
        self.device = JackalDevice(robot, session=self.s_world, namespace=f"rmw{next(_ns)}/robot2", device=device)
        self.malformed: list[str] = []
        self.odoms: list = []
        self.driver = JackalDriver(2, WIDE, session=self.s_agent, on_malformed=self.malformed.append,
                                   on_odom=self.odoms.append, **settings, **self.device.driver_params(), **cfg)

    def __enter__(self) -> "Rig":
        self.device.start()
        try:
            self.driver.open()
        except BaseException:
            self.device.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.driver.close()
        self.device.close()

    def target(self, t: float = 0.0):
        self.device.take_commands(t)
        return self.device.target


def test_driver_and_simulated_jackal_meet_on_rmw_zenoh_and_show_in_the_graph(sessions):
    graph = rz.RosGraph(sessions[0], 0)
    with Rig(sessions) as rig:
        ns = "/" + rig.device.namespace
        assert rig.odoms and rig.driver.read().pose == pytest.approx((1.0, -2.0, 0.5))  # opened on its odometry
        assert rig.driver.cmd_key == rig.device.cmd_key and rig.driver.cmd_key.startswith(f"0{ns}/cmd_vel/")
        assert rig.driver.command(0.5, 0.3) == (0.5, 0.3)
        assert wait_for(lambda: rig.target() == (0.5, 0.3)), (rig.device.target, rig.device.counters)
        assert rig.device.node.counters == {} and rig.driver.node.counters == {}  # every sample had its attachment
        rig.device.lockstep(2.0)
        rig.device.publish_scan(2.5, -math.pi / 2, math.pi / 179, 5.0, [1.5] * 180)
        scan = wait_for(lambda: rig.driver.read_scan())
        assert scan and scan.ranges == pytest.approx((1.5,) * 180) and scan.stamp == pytest.approx(rig.device.device_time(2.5), abs=1e-9)
        ours, theirs = f"{ns}/stack_agent", f"{ns}/jackal_sim"
        assert wait_for(lambda: {ours, theirs} <= graph.nodes()), graph.nodes()
        want = {("cmd_vel", rz.PUBLISHER): ours, ("cmd_vel", rz.SUBSCRIPTION): theirs,
                ("platform/odom/filtered", rz.PUBLISHER): theirs, ("platform/odom/filtered", rz.SUBSCRIPTION): ours,
                ("sensors/lidar2d_0/scan", rz.PUBLISHER): theirs, ("sensors/lidar2d_0/scan", rz.SUBSCRIPTION): ours}
        for (topic, kind), node in want.items():  # each entity's token arrives on its own
            assert wait_for(lambda: [e.node for e in graph.endpoints(f"{ns}/{topic}", kind)] == [node]), (topic, kind)
        assert {e.qos for e in graph.endpoints(f"{ns}/sensors/lidar2d_0/scan")} == {rz.SENSOR_QOS}
        assert rig.malformed == [] and graph.counters == {}
    assert wait_for(lambda: not {ours, theirs} & graph.nodes()), graph.nodes()
    graph.close()


def test_malformed_attachments_and_keys_are_counted_never_raised(sessions):
    with Rig(sessions, odom_timeout=5.0) as rig:
        s_world, s_agent = rig.s_world, rig.s_agent
        key = rig.driver.odom_key
        good = rz.Attachment(1, time.time_ns(), bytes(16))
        rig.device.lockstep(0.0)  # the device's own odometry stops: only ours below
        odo = encode_odometry(50.0, 7.0, 8.0, 0.0, 0.1, 0.0)
        s_world.put(key, odo)  # no attachment
        s_world.put(key, odo, attachment=b"\x01\x02\x03")  # not rmw_zenoh's
        s_world.put(key, odo, attachment=good.encode()[:-1] + b"")  # one byte short
        s_world.put(key.rsplit("/", 1)[0] + "/" + rz.HASH_NOT_SUPPORTED, odo, attachment=good.encode())  # Humble
        s_world.put(key.rsplit("/", 2)[0] + "/nav_msgs::msg::dds_::Path_/RIHS01_00", odo, attachment=good.encode())
        s_world.put(key, b"junk", attachment=rz.Attachment(2, 0, bytes(16)).encode())  # attached, not CDR
        s_world.put(key, encode_odometry(52.0, 7.0, 8.0, 0.0, 0.2, 0.0), attachment=rz.Attachment(5, 0, bytes(16)).encode())
        assert wait_for(lambda: rig.driver.read().stamp == 52.0), rig.driver.counters
        c = rig.driver.counters
        assert (c["rmw_no_attachment"], c["rmw_bad_attachment"], c["rmw_hash_mismatch"], c["rmw_type_mismatch"],
                c["odom_not_cdr"], c["rmw_lost"]) == (1, 2, 1, 1, 1, 1), c
        assert rig.driver.node.counters["lost"] == 2  # one gap (2 -> 5) of two samples
        assert sorted(rig.malformed) == sorted(["jackal/rmw_no_attachment", "jackal/rmw_bad_attachment",
                                                "jackal/rmw_bad_attachment", "jackal/rmw_hash_mismatch",
                                                "jackal/rmw_type_mismatch", "jackal/odom_not_cdr"])  # lost: not malformed
        assert rig.driver.read().v == 0.2 and rig.driver.fault is None
        # the robot's side drops commands as rmw_zenoh_cpp does, and keeps its target
        rig.driver.command(0.3, 0.1)
        assert wait_for(lambda: rig.target() == (0.3, 0.1))
        s_agent.put(rig.device.cmd_key, encode_twist(1.0, 1.0))
        s_agent.put(rig.device.cmd_key, encode_twist(1.0, 1.0), attachment=b"\x00" * 33)
        assert wait_for(lambda: rig.device.counters.get("cmd_bad_attachment")), rig.device.counters
        rig.device.take_commands(0.0)
        d = rig.device.counters
        assert (d["cmd_no_attachment"], d["cmd_bad_attachment"]) == (1, 1) and rig.device.target == (0.3, 0.1)


def test_the_example_fleet_file_is_on_rmw_zenoh():
    from conftest import ROOT
    from stack.scenario import load_scenario

    sc = load_scenario(str(ROOT / "deploy" / "robots" / "jackal-rmw-zenoh.yaml"))
    for r in sc.robots:
        cfg = JackalConfig(**r.driver_params["jackal"])
        assert (r.driver, cfg.transport, cfg.node_config(r.id).namespace) == ("jackal", "rmw_zenoh", f"/robot{r.id}")


def test_open_without_the_robots_router_names_rmw_zenohd(sessions):
    drv = JackalDriver(4, WIDE, session=sessions[0], transport="rmw_zenoh", namespace=f"rmw{next(_ns)}/nobody",
                       open_timeout=0.2)
    with pytest.raises(DriverError, match=r"no odometry on 0/rmw\d+/nobody/platform/odom/filtered/nav_msgs::msg::dds_::"
                                          r"Odometry_/RIHS01_\w+ within 0.2 s \(is the robot's rmw_zenohd up, namespace right\?\)"):
        drv.open()
    drv.close()


def _hardware_run(sessions, transport: str) -> tuple[list, int]:
    """The hardware-like Jackal (own rates, robot clock ahead) in 1 s of lock-step: what the driver receives."""
    hw = {"ideal": False, "odom_rate_hz": 20.0, "lidar_rate_hz": 5.0, "clock_offset_s": 3.7}
    with Rig(sessions, transport, device=hw, odom_timeout=5.0) as rig:
        dev = rig.device
        dev.lockstep(0.0)
        dev.report(0.0, Body(1.0, -2.0, 0.5, 0.0, 0.0))
        for k in range(10):
            t = 0.1 * k
            dev.publish_scan(t, -math.pi / 2, math.pi / 179, 5.0, [2.0 + t] * 180)
            dev.take_commands(t)
            dev.motion(t + 0.1)
            dev.report(t + 0.1, Body(1.0 + 0.3 * (t + 0.1), -2.0, 0.5, 0.3, 0.0))
        sent = dev.counters.get("odom", 0)
        assert wait_for(lambda: rig.driver.counters.get("odom", 0) >= sent, 3.0), (rig.driver.counters, sent)
        lockstep = [(o.stamp, tuple(round(p, 9) for p in o.pose), o.v) for o in rig.odoms if o.stamp < 100.0]
        assert rig.malformed == []
        return lockstep, dev.counters.get("scan", 0)


def test_hardware_like_settings_are_the_same_over_both_transports(sessions):
    bridge, rmw = _hardware_run(sessions, "bridge"), _hardware_run(sessions, "rmw_zenoh")
    assert rmw == bridge
    odoms, scans = rmw
    assert len(odoms) == 21 and scans == 5  # 20 Hz and 5 Hz over 1 s (odometry at 0 s too)
    assert [round(s - 3.7, 6) for s, _, _ in odoms] == [round(0.05 * k, 6) for k in range(21)]  # the robot's clock
    assert odoms[0][1] == (0.0, 0.0, 0.0) and odoms[1][1] == pytest.approx((0.015, 0.0, 0.0), abs=1e-9)  # odom frame


# --- a fleet on rmw_zenoh ----------------------------------------------------------------------
@pytest.mark.fleet
def test_a_jackal_fleet_on_rmw_zenoh_matches_the_bridge(tmp_path):
    reports = {}
    for transport in ("bridge", "rmw_zenoh"):
        d = scenario_dict()
        d["robot"]["jackal"] = {"transport": transport}
        d["robot"]["device"] = {"ideal": True}  # the transports compared on one device (hardware-like: test_hil_fleet)
        out = tmp_path / transport
        proc, rep = run_fleet(write_scenario(tmp_path / f"{transport}.yaml", d), out, "--driver", "jackal", "--no-plots")
        assert proc.returncode == 0 and rep and rep["success"], proc.stdout[-3000:] + proc.stderr[-3000:]
        assert set(rep["drivers"].values()) == {"jackal"}
        assert all(r["driver_fault"] is None for r in rep["robots"].values())
        reports[transport] = rep
    a, b = reports["bridge"], reports["rmw_zenoh"]
    assert a["late_steps"] == 0 == b["late_steps"]  # no wall-clock bound expired: both are the lock-step run
    assert b["collisions"] == a["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    # The same CDR on both transports and lock-step device fleets repeat to the bit (issue 16: a cmd_vel that
    # reached the device after the agent's answer once made three bridge runs differ by 0.3 mm): the same run.
    assert lockstep_report(b) == lockstep_report(a)
