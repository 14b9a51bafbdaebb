"""Lidar sources apart from the base: each sensor driver against its simulated device, at the device's own rate
and beam layout, with samples missing and bytes broken; the robot-centred scan the policy sees; bad settings.

The devices scan a known room (a wall at x = 3 m in the world frame, nothing else within range), cast by a
plain function in place of the world's rays, so every range is known: the ray at world bearing ``a`` from
``(x, y)`` meets the wall at ``(3 - x) / cos(a)``.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest

from conftest import run_cli, scenario_dict, wait_for, write_scenario
from test_jackal import sessions  # noqa: F401 - the module's router and two client sessions (agent, world)
from stack.agents.lidar import scan_from_lidar, to_robot_frame
from stack.drivers import rplidar_protocol as rp
from stack.drivers.lidar import LidarError
from stack.drivers.lidar_ros2 import Ros2Lidar
from stack.drivers.ros2cdr import encode_laserscan
from stack.drivers.rplidar import RplidarLidar
from stack.scenario import ScenarioError, parse_scenario
from stack.sim_bridge.devices import Body, DeviceError
from stack.sim_bridge.ros2_lidar_sim import Ros2LidarDevice
from stack.sim_bridge.rplidar_sim import RplidarDevice

WALL_X, RANGE = 3.0, 5.0
STILL = Body(0.0, 0.0, 0.0, 0.0, 0.0)
_ns = itertools.count()


def wall(x, y, yaw, angles):
    """The world's rays from (x, y, yaw) at ``angles`` (sensor frame): the wall at x = 3, else RANGE."""
    c = np.cos(yaw + np.asarray(angles, float))
    with np.errstate(divide="ignore"):
        t = np.where(c > 1e-9, (WALL_X - x) / c, np.inf)
    return np.minimum(t, RANGE)


def robot(lidar: dict, rid: int = 0):
    d = scenario_dict()
    d["robot"]["lidar"] = {"beams": 181, "fov_deg": 180, "range": RANGE} | lidar
    return parse_scenario(d).robot(rid)


def truth(beams: np.ndarray) -> np.ndarray:
    """What the robot at the origin should see at robot-frame bearings ``beams``."""
    return wall(0.0, 0.0, 0.0, beams)


def run(dev, seconds: float, dt: float = 0.1, body: Body = STILL, t0: float = 0.0, pause: float = 0.002) -> float:
    """The world's reports to ``dev`` over ``seconds`` of sim time (lock-step: the body stands at ``body``)."""
    t = t0
    for _ in range(int(round(seconds / dt))):
        dev.report(t, t + dt, body, body)
        t += dt
        time.sleep(pause)  # the host reads as the bytes come (a real link's pace is the device's, not ours)
    return t


class RplidarRig:
    def __init__(self, lidar: dict | None = None, **driver):
        self.robot = robot({"source": "rplidar"} | (lidar or {}))
        self.dev = RplidarDevice(self.robot, seed=4)
        self.dev.ray_caster = wall
        self.dev.start()
        self.scans, self.malformed = [], []
        self.lidar = RplidarLidar(0, port=self.dev.driver_params()["port"], on_scan=self.scans.append,
                                  on_malformed=self.malformed.append, **(dict(self.robot.lidar.params) | driver))

    def close(self):
        self.lidar.close()
        self.dev.close()


@pytest.fixture
def rplidar():
    rigs = []
    yield lambda *a, **kw: rigs.append(RplidarRig(*a, **kw)) or rigs[-1]
    for r in rigs:
        r.close()


# --- rplidar ---------------------------------------------------------------------------------
def test_rplidar_driver_reads_its_simulated_a1_at_the_real_rate_and_layout(rplidar):
    rig = rplidar()
    rig.lidar.open()
    assert rig.lidar.info.series == "A1" and rig.lidar.health == (rp.HEALTH_GOOD, 0)
    run(rig.dev, 4.0)
    assert wait_for(lambda: len(rig.scans) == rig.dev.scans_sent, 2.0)
    n = len(rig.scans)
    assert 20 <= n <= 23  # 5.5 Hz (+-2 % per revolution) over 4 s of the device's time, the first one waited for
    sizes = [len(s.angles) for s in rig.scans]
    assert all(340 <= k <= 380 for k in sizes), sizes  # 2 kHz samples at 5.5 Hz: about 364 a revolution
    a = np.degrees(-rig.scans[-1].angles) % 360  # back to the device's clockwise degrees
    assert np.mean(np.abs(a - np.round(a)) > 0.01) > 0.9  # angles are not whole degrees
    assert np.degrees(np.abs(rig.scans[3].angles[0] - rig.scans[4].angles[0])) > 0.01  # nor the same every turn
    valid = [np.isfinite(s.ranges) for s in rig.scans]
    behind = [np.cos(s.angles) < 0.59 for s in rig.scans]  # no wall within 5 m there: invalid (distance 0)
    assert all(not v[b].any() for v, b in zip(valid, behind))
    front = np.concatenate([v[np.cos(s.angles) > 0.61] for v, s in zip(valid, rig.scans)])
    assert 0.97 < front.mean() < 1.0  # the device's 1 % invalid samples are missing, the rest read the wall
    s = rig.scans[-1]
    ok = np.isfinite(s.ranges)
    assert s.ranges[ok] == pytest.approx(wall(0, 0, 0, s.angles[ok]), abs=1e-3)  # distance_q2: 0.25 mm
    stamps = [s.stamp for s in rig.scans]
    assert stamps == sorted(stamps)
    assert rig.malformed == [] and rig.lidar.counters.get("bad_sample", 0) == 0


def test_rplidar_scan_is_the_robot_centred_layout_the_policy_expects(rplidar):
    rig = rplidar({"device": {"invalid_prob": 0.3}})  # samples missing: 30 % read 0
    rig.lidar.open()
    run(rig.dev, 1.0)
    assert wait_for(lambda: len(rig.scans) >= 4, 2.0)
    scan = scan_from_lidar(rig.robot, rig.scans[-1], 0, 1.0)
    assert len(scan.ranges) == 181 and scan.range_max == RANGE
    beams = np.linspace(-math.pi / 2, math.pi / 2, 181)
    want = truth(beams)
    # each beam takes the nearest valid sample within 1.5 spacings (1.5 deg): the wall's range there
    near = np.abs(want - np.array(scan.ranges)) < 0.15
    assert near.mean() > 0.95, np.array(scan.ranges)[~near]


def test_a_mounted_lidar_gives_the_robot_centred_scan(rplidar):
    """Mounted 0.25 m ahead of the centre and turned around (its 0 deg mark backwards): the same scan."""
    rig = rplidar({"mount": [0.25, 0.1, 180], "device": {"invalid_prob": 0.0}})
    rig.lidar.open()
    run(rig.dev, 1.0)
    assert wait_for(lambda: len(rig.scans) >= 4, 2.0)
    scan = scan_from_lidar(rig.robot, rig.scans[-1], 0, 1.0)
    beams = np.linspace(-math.pi / 2, math.pi / 2, 181)
    assert np.array(scan.ranges)[60:121] == pytest.approx(truth(beams)[60:121], abs=0.06)
    # 1 m straight back from the mount point; a no-return ray (7 m > range_max 6 m) to the right of the robot
    b, r = to_robot_frame([0.0, math.pi / 2], [1.0, 7.0], (0.25, 0.1, math.pi), 6.0)
    assert b == pytest.approx([math.atan2(0.1, -0.75), math.atan2(-5.9, 0.25)])
    assert r == pytest.approx([math.hypot(0.75, 0.1), 6.0])  # no return stays no return


def test_rplidar_a2_motor_runs_on_pwm(rplidar):
    rig = rplidar({"rplidar": {"model": "A2"}})
    assert rig.dev.pty.spinning is False
    rig.lidar.open()
    assert rig.dev.pty.pwm == rp.DEFAULT_PWM and rig.lidar.info.series == "A2"
    run(rig.dev, 2.0)
    assert wait_for(lambda: len(rig.scans) >= 19, 2.0)  # 10 Hz at PWM 660
    assert all(180 <= len(s.angles) <= 220 for s in rig.scans)
    rig.lidar.close()
    assert wait_for(lambda: rig.dev.pty.pwm == 0 and rig.dev.pty.scanning is False, 2.0)


def test_broken_bytes_are_counted_drops_and_scans_go_on(rplidar):
    rig = rplidar({"device": {"corrupt_prob": 0.01}})
    rig.lidar.open()
    run(rig.dev, 3.0)
    assert wait_for(lambda: len(rig.scans) >= 14, 2.0)
    bad = rig.lidar.counters.get("bad_sample", 0)
    assert bad > 0 and rig.malformed.count("rplidar/bad_sample") == bad
    # direct: garbage between packets costs one count per loss of step, and no sample
    lid = RplidarLidar(1)
    pkt = [rp.encode_sample(i == 0, 47, i * 1.0, 1000.0) for i in range(60)]
    lid.feed(b"".join(pkt[:30]) + b"\x00\x00\x00" + b"".join(pkt[30:]) + rp.encode_sample(True, 47, 0.5, 900.0))
    assert lid.counters["bad_sample"] == 1 and lid.scans == 1 and len(lid.read().angles) == 60
    lid.feed(b"".join(pkt[:10]) + rp.encode_sample(True, 47, 0.5, 900.0))  # revolutions of 1 and 10 samples
    assert lid.counters["short_scan"] == 2 and lid.scans == 1


def test_rplidar_open_errors_are_one_line(rplidar, tmp_path):
    with pytest.raises(LidarError, match=r"cannot open .*nope") as e:
        RplidarLidar(0, port=str(tmp_path / "nope")).open()
    assert "\n" not in str(e.value)
    rig = rplidar()
    rig.dev.pty.health = (rp.HEALTH_ERROR, 0x8002)
    rig.lidar.open()  # a protection stop that a RESET clears
    assert rig.lidar.health == (rp.HEALTH_GOOD, 0) and rig.dev.pty.counters["req_40"] == 1
    rig.lidar.close()
    rig.dev.pty.health, rig.dev.pty.error_persists = (rp.HEALTH_ERROR, 0x8002), True
    with pytest.raises(LidarError, match=r"protection stop \(error code 0x8002\) after a RESET"):
        rig.lidar.open()
    rig.dev.pty.shutdown()  # the sensor is gone: no answer, named
    mute = rplidar()
    mute.dev.pty._halt.set()
    mute.dev.pty._thread.join(timeout=2.0)  # gone before we ask (its select could still answer GET_HEALTH under load)
    assert not mute.dev.pty._thread.is_alive()
    with pytest.raises(LidarError, match="no answer to GET_HEALTH within 0.2 s"):
        RplidarLidar(0, port=mute.dev.driver_params()["port"], open_timeout=0.2).open()


# --- ros2 ------------------------------------------------------------------------------------
class _Keys:
    def __init__(self):
        self.fleet = f"lidartest{next(_ns)}"


def ros2_rig(sessions, lidar: dict, **kw):
    s_agent, s_world = sessions
    r = robot({"source": "ros2"} | lidar)
    dev = Ros2LidarDevice(r, session=s_world, keys=_Keys(), seed=2)
    dev.ray_caster = wall
    dev.start()
    dev.lockstep(0.0)
    scans, malformed = [], []
    drv = Ros2Lidar(0, session=s_agent, on_scan=scans.append, on_malformed=malformed.append,
                    **(dict(r.lidar.params) | dev.driver_params() | kw))
    return r, dev, drv, scans, malformed


@pytest.mark.parametrize("transport", ["bridge", "rmw_zenoh"])
def test_ros2_lidar_driver_reads_its_simulated_device_at_its_rate(sessions, transport):
    r, dev, drv, scans, malformed = ros2_rig(sessions, {"ros2": {"transport": transport},
                                                       "device": {"clock_offset_s": 100.0}})
    with drv:
        time.sleep(0.3)  # the subscription reaches the router
        run(dev, 2.0)
        assert wait_for(lambda: len(scans) == dev.scans_sent == 31, 3.0), (len(scans), dev.scans_sent)  # 15 Hz, 0..2 s
    s = scans[-1]
    assert len(s.angles) == 541 and s.angles[0] == pytest.approx(-math.radians(135))  # the device's own layout
    assert [x.stamp for x in scans] == pytest.approx([100.0 + i / 15 for i in range(31)], abs=1e-6)  # its clock
    ahead = np.cos(s.angles) > 0.7
    assert s.ranges[ahead] == pytest.approx(wall(0, 0, 0, s.angles[ahead]), abs=1e-4)
    assert (s.ranges[~(np.cos(s.angles) > 0.6)] == RANGE).all()  # no return (+inf on the wire) reads range_max
    scan = scan_from_lidar(r, s, 0, 0.0)
    assert np.array(scan.ranges) == pytest.approx(truth(np.linspace(-math.pi / 2, math.pi / 2, 181)), abs=1e-3)
    assert malformed == []


def test_ros2_lidar_with_scans_missing_and_bad_payloads(sessions):
    r, dev, drv, scans, malformed = ros2_rig(sessions, {"device": {"drop_prob": 0.3, "rate_hz": 10.0}})
    with drv:
        time.sleep(0.3)
        run(dev, 3.0)
        assert wait_for(lambda: len(scans) == dev.scans_sent, 3.0)
        assert dev.dropped > 3 and dev.scans_sent + dev.dropped == 31  # the lost ones never came
        bad = sessions[1].declare_publisher(drv.key)
        bad.put(b"not cdr")
        bad.put(encode_laserscan(1.0, 0.0, 0.01, 5.0, [])[:-1] + b"")  # no ranges: not a usable scan
        assert wait_for(lambda: len(malformed) == 2, 2.0), malformed
        bad.undeclare()
    assert set(malformed) <= {"ros2/scan_not_cdr", "ros2/scan_undecodable", "ros2/scan_bad_value"}
    assert drv.scans == len(scans) and drv.age() is not None


# --- settings -------------------------------------------------------------------------------
def test_bad_lidar_settings_are_one_line_errors(tmp_path):
    d = scenario_dict()
    for lidar, words in [({"source": "velodyne"}, "robots[1].lidar.source: expected one of world, ros2, rplidar"),
                         ({"source": "rplidar", "rplidar": {"baud": 9600}}, "robots[1].lidar.rplidar.baud: expected 115200"),
                         ({"rplidar": {"bogus": 1}}, "robots[1].lidar.rplidar.bogus: unknown field"),
                         ({"mount": [0.1, 0.0]}, "robots[1].lidar.mount: expected 3 numbers, got 2"),
                         ({"source": "ros2", "device": {"rate_hz": 0}}, "robots[1].lidar.device: rate_hz must be > 0"),
                         ({"device": {"rate_hz": 5}}, "robots[1].lidar.device.rate_hz: unknown field")]:
        d["robots"][1]["lidar"] = lidar
        with pytest.raises(ScenarioError, match=words.replace("[", r"\[").replace("]", r"\]")):
            parse_scenario(d, "s.yaml")
    d["robots"][1]["lidar"] = {"source": "rplidar", "rplidar": {"model": "A3"}}
    p = run_cli(["stack-fleet", "run", str(write_scenario(tmp_path / "bad.yaml", d)), "--out", str(tmp_path / "o")])
    assert p.returncode == 2 and "robots[1].lidar.rplidar.model: expected one of A1, A2" in p.stderr, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1
    with pytest.raises(DeviceError, match="robot 0: rplidar lidar device: quality must be"):
        RplidarDevice(robot({"source": "rplidar"}), device={"quality": 99})
