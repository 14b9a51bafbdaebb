"""The site frame on the globe: geodesy, the MAVLink driver placed by GLOBAL_POSITION_INT around a datum,
and the world's lidar cast at a pose of the device's choosing.

Geodesy is checked against published WGS 84 arc lengths and against pymavlink's ``mavextra``
(its spherical model, code we did not write). The driver runs in wall time against the
world's simulated rover device (``RoverDevice``: hardware-like, EKF origin where it booted),
whose body a small thread moves as the rover's controllers ask.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time

import numpy as np
import pybullet as p
import pytest
from pymavlink import mavextra, mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from conftest import scenario_dict, wait_for
from stack.drivers import DriverLimits
from stack.drivers.mavlink import MavlinkConfig, MavlinkDriver
from stack.models.geodesy import (WGS84_A, WGS84_E2, check_datum, geodetic_to_ne, geodetic_to_site, ne_to_geodetic,
                                  site_to_geodetic)
from stack.scenario import RobotConfig, parse_scenario
from stack.sim_bridge.devices import Body, DeviceError
from stack.sim_bridge.devices_mavlink import RoverDevice
from stack.sim_bridge.world import World

DATUM = (47.3977, 8.5456, 488.0)
LIMITS = DriverLimits(v_max=1.0, w_max=2.0, cmd_timeout=5.0)
R_PYMAVLINK = 6378100.0  # [m] mavextra's radius_of_earth (ArduPilot's LOCATION_SCALING_FACTOR sphere)


def radii(lat: float) -> tuple[float, float]:
    """WGS 84 meridian (M) and prime-vertical (N) radii of curvature at ``lat`` [deg]."""
    s2 = math.sin(math.radians(lat)) ** 2
    return WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s2) ** 1.5, WGS84_A / math.sqrt(1 - WGS84_E2 * s2)


# --- geodesy -------------------------------------------------------------------------------
@pytest.mark.parametrize("datum", [DATUM, (0.0, 0.0, 0.0), (-35.363261, 149.165230, 584.0), (69.6, 18.9, 10.0),
                                   (12.0, 179.99, 5.0)])
def test_round_trips_within_a_millimetre_over_5_km(datum):
    rng = np.random.default_rng(1)
    for x, y in rng.uniform(-5000.0, 5000.0, (200, 2)):
        lat, lon, alt = site_to_geodetic(datum, x, y)
        assert alt == datum[2] and -180.0 <= lon <= 180.0
        assert geodetic_to_site(datum, lat, lon, alt) == pytest.approx((x, y), abs=1e-3)
        north, east = geodetic_to_ne(datum, *ne_to_geodetic(datum, y, x)[:2])
        assert (east, north) == pytest.approx((x, y), abs=1e-3)
    # degE7 on the wire: a fix rounded to 1e-7 deg is still within 1.1 cm
    lat, lon, _ = site_to_geodetic(datum, 1234.5, -678.9)
    assert geodetic_to_site(datum, round(lat * 1e7) * 1e-7, round(lon * 1e7) * 1e-7) == \
        pytest.approx((1234.5, -678.9), abs=0.012)


def test_metric_against_the_published_length_of_a_degree():
    """The series for the length of a degree on WGS 84 (as in, e.g., Wikipedia's "Latitude", "Length of a degree"):
    of latitude 111132.954 - 559.822 cos 2phi + 1.175 cos 4phi, of longitude 111412.84 cos phi - 93.5 cos 3phi
    + 0.118 cos 5phi [m] (truncated series: 5e-7 and 4e-6 of a degree; a site is metric to a few mm over 5 km)."""
    for lat in (0.0, 30.0, 45.0, 60.0):
        phi = math.radians(lat)
        d = (lat, 10.0, 0.0)
        _, y1 = geodetic_to_site(d, lat - 0.0005, 10.0)
        _, y2 = geodetic_to_site(d, lat + 0.0005, 10.0)
        x1, _ = geodetic_to_site(d, lat, 10.0 - 0.0005)
        x2, _ = geodetic_to_site(d, lat, 10.0 + 0.0005)
        assert (y2 - y1) * 1000 == pytest.approx(111132.954 - 559.822 * math.cos(2 * phi) + 1.175 * math.cos(4 * phi),
                                                 abs=0.05)
        assert (x2 - x1) * 1000 == pytest.approx(111412.84 * math.cos(phi) - 93.5 * math.cos(3 * phi)
                                                 + 0.118 * math.cos(5 * phi), abs=0.3)
    d = (45.0, 0.0, 0.0)  # the ground falls away below the tangent plane, but distances along it stay metric
    lat, lon, _ = site_to_geodetic(d, 4000.0, 0.0)
    assert geodetic_to_site(d, lat, lon) == pytest.approx((4000.0, 0.0), abs=1e-4)


def test_pymavlink_spherical_offsets_agree_up_to_the_earth_model():
    """mavextra.gps_offset moves on a 6 378 100 m sphere: its metres are ours times R / M north and R / N east
    (M, N: WGS 84's radii of curvature, plus the datum's 488 m of height: arcs up there are longer)."""
    m, n = (r + DATUM[2] for r in radii(DATUM[0]))
    for east, north in ((0.0, 100.0), (100.0, 0.0), (-30.0, 40.0)):
        lat, lon = mavextra.gps_offset(DATUM[0], DATUM[1], east, north)
        x, y = geodetic_to_site(DATUM, lat, lon)
        assert (x, y) == pytest.approx((east * n / R_PYMAVLINK, north * m / R_PYMAVLINK), abs=2e-3)
        assert (x, y) == pytest.approx((east, north), abs=0.2)  # and the model difference is 0.13-0.17 %
    lat, lon, _ = site_to_geodetic(DATUM, 300.0, 400.0)  # and back: mavextra's haversine on its 6 371 km sphere
    assert mavextra.distance_lat_lon(DATUM[0], DATUM[1], lat, lon) == \
        pytest.approx(math.hypot(300.0 * 6_371_000.0 / n, 400.0 * 6_371_000.0 / m), abs=2e-3)


def test_check_datum_one_line_errors():
    assert check_datum([47, 8, 400]) == (47.0, 8.0, 400.0)
    for bad, words in (([1.0, 2.0], "datum must be \\[lat_deg, lon_deg, alt_m\\]"), ("47,8,0", "datum must be"),
                       ([95.0, 0.0, 0.0], "datum latitude must be within \\[-89, 89\\]"),
                       ([0.0, 181.0, 0.0], "datum longitude must be within \\[-180, 180\\]"),
                       ([0.0, 0.0, float("nan")], "datum altitude must be a finite number"),
                       ([True, 0.0, 0.0], "datum latitude must be a finite number")):
        with pytest.raises(ValueError, match=words):
            check_datum(bad)


# --- the driver against the simulated rover --------------------------------------------------
class Rover:
    """The world's simulated rover device (hardware-like: EKF origin at boot) in real time, its body moved
    by a thread as the rover's controllers ask, and a MAVLink driver on it."""

    def __init__(self, boot, *, site_datum=DATUM, device=None, **driver):
        robot = RobotConfig(id=1, role="leader", pose=boot, driver="mavlink",
                            driver_params={"mavlink": {"position_std": 1e-9}})
        self.dev = RoverDevice(robot, device={"ideal": False, "ekf_origin": "boot", **(device or {})},
                               site_datum=site_datum)
        self.dev.start()
        self.body = Body(*boot, 0.0, 0.0)
        self.teleport: tuple[float, float, float] | None = None
        self._halt = threading.Event()
        self._mover = threading.Thread(target=self._move, daemon=True)
        self._mover.start()
        params = {"position_rate": 20.0, "attitude_rate": 20.0, "ack_timeout": 0.3, "position_std": 0.25,
                  "datum": site_datum, **driver}  # the scenario's site.datum, as the agent passes it
        self.driver = MavlinkDriver(1, LIMITS, **self.dev.driver_params(), **params)

    def _move(self, dt: float = 0.01) -> None:
        while not self._halt.wait(dt):
            v, w = self.dev.motion(0.0)
            b = self.body
            if self.teleport is not None:
                b, self.teleport = Body(*self.teleport, 0.0, 0.0), None
            else:
                b = Body(b.x + v * dt * math.cos(b.yaw), b.y + v * dt * math.sin(b.yaw), b.yaw + w * dt, v, w)
            self.body = b
            self.dev.report(0.0, b)

    def open(self) -> "Rover":
        self.driver.open()
        return self

    def settled_fix(self, where: tuple[float, float], tol: float = 0.02):
        """Wait until the driver's fix is at ``where`` (and a later odometry sample exists); return (fix, odometry)."""
        assert wait_for(lambda: (f := self.driver.position_fix()) is not None
                        and math.dist(f[:2], where) < tol, 3.0), (self.driver.position_fix(), where)
        time.sleep(0.15)  # a few more samples of both streams, the body still
        return self.driver.position_fix(), self.driver.read()

    def close(self) -> None:
        self.driver.close()
        self._halt.set()
        self._mover.join(1.0)
        self.dev.close()


BOOT_A = (3.0, -2.0, math.radians(30.0))
BOOT_B = (-4.0, 5.0, math.radians(-90.0))


def test_fix_in_the_site_frame_while_local_position_is_from_the_boot_point():
    r = Rover(BOOT_A).open()
    station = None
    try:
        fix, odo = r.settled_fix(BOOT_A[:2])
        assert fix[2] == 0.25  # the configured position_std
        assert odo.pose[:2] == pytest.approx((0.0, 0.0), abs=1e-3)  # LOCAL_POSITION_NED: the EKF origin is here
        assert math.remainder(odo.pose[2] - BOOT_A[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-3)
        assert r.dev.rover.intervals[mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT] == pytest.approx(0.05)  # asked at 20 Hz
        r.driver.command(0.5, 0.0)
        time.sleep(1.5)
        r.driver.command(0.0, 0.0)
        assert wait_for(lambda: abs(r.body.v) < 1e-9, 3.0)
        body = r.body
        assert math.dist((body.x, body.y), BOOT_A[:2]) > 0.4  # it drove
        fix, odo = r.settled_fix((body.x, body.y))
        assert odo.pose[:2] == pytest.approx((body.x - BOOT_A[0], body.y - BOOT_A[1]), abs=0.02)  # from boot
        # the same GLOBAL_POSITION_INT through pymavlink's own conversion (its 6 378 100 m sphere)
        station = mavutil.mavlink_connection(f"udpout:127.0.0.1:{r.dev.rover.port}", source_system=254,
                                             dialect="ardupilotmega")
        station.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        g = station.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=2.0)
        lat, lon = g.lat * 1e-7, g.lon * 1e-7
        assert mavextra.distance_lat_lon(DATUM[0], DATUM[1], lat, lon) == pytest.approx(math.hypot(*fix[:2]), abs=0.02)
        assert mavextra.gps_offset(DATUM[0], DATUM[1], *fix[:2]) == pytest.approx((lat, lon), abs=2e-7)
        assert geodetic_to_site(DATUM, lat, lon, g.alt * 1e-3) == pytest.approx(fix[:2], abs=1e-6)
        assert r.driver.liveness().keys() >= {"global_position", "local_position", "odom"}
    finally:
        if station is not None:
            station.close()
        r.close()


def test_two_rovers_booted_apart_agree_in_the_site_frame():
    a, b = Rover(BOOT_A).open(), None
    try:
        b = Rover(BOOT_B).open()
        b.settled_fix(BOOT_B[:2])
        spot = (1.0, 1.5, 0.0)
        a.teleport = b.teleport = spot  # both stand on the same spot of the site
        fa, oa = a.settled_fix(spot[:2])
        fb, ob = b.settled_fix(spot[:2])
        assert fa[:2] == pytest.approx(fb[:2], abs=0.02)  # agree where they are
        # while their own frames (LOCAL_POSITION_NED from each EKF origin) differ by the boot offset
        offset = (oa.pose[0] - ob.pose[0], oa.pose[1] - ob.pose[1])
        assert offset == pytest.approx((BOOT_B[0] - BOOT_A[0], BOOT_B[1] - BOOT_A[1]), abs=0.02)
    finally:
        a.close()
        if b is not None:
            b.close()


def test_without_a_datum_fixes_are_local_position_ned_as_before():
    r = Rover(BOOT_A, site_datum=None).open()
    try:
        assert r.driver.config.datum is None
        assert wait_for(lambda: r.driver.position_fix() is not None, 3.0)
        time.sleep(0.2)
        fix, odo = r.driver.position_fix(), r.driver.read()
        assert fix[:2] == pytest.approx((0.0, 0.0), abs=1e-3) == odo.pose[:2]  # from the EKF origin (boot)
        assert r.dev.rover.intervals.get(mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 0.0) == 0.0  # never asked for
        assert "global_position" not in r.driver.liveness()
    finally:
        r.close()


def test_set_ekf_origin_moves_local_position_ned_to_the_site_frame():
    r = Rover(BOOT_A, datum=list(DATUM), set_ekf_origin=True).open()  # a list, as from YAML
    try:
        assert r.driver.counters.get("origin_set") == 1 and "origin_refused" not in r.driver.counters
        assert r.driver.ekf_origin == pytest.approx(DATUM, abs=1e-7)
        fix, odo = r.settled_fix(BOOT_A[:2])
        assert odo.pose[:2] == pytest.approx(BOOT_A[:2], abs=0.01)  # LOCAL_POSITION_NED now from the datum
    finally:
        r.close()


def test_a_vehicle_keeping_its_origin_is_a_warning_not_a_failure(caplog):
    r = Rover(BOOT_A, set_ekf_origin=True, command_retries=0)
    r.dev.rover._on_origin = lambda m, t: None  # an EKF that already fuses GPS: the message is ignored, no reply
    try:
        r.open()
        assert r.driver.counters.get("origin_refused") == 1 and "kept its EKF origin" in caplog.text
        fix, odo = r.settled_fix(BOOT_A[:2])  # fixes still in the site frame, odometry from its own origin
        assert odo.pose[:2] == pytest.approx((0.0, 0.0), abs=1e-3)
    finally:
        r.close()


def test_the_site_datum_reaches_the_device_and_settings_win():
    robot = RobotConfig(id=1, role="leader", pose=BOOT_A, driver="mavlink")
    assert RoverDevice(robot, site_datum=[10.0, 20.0, 30.0]).datum == (10.0, 20.0, 30.0)
    assert RoverDevice(robot, site_datum=DATUM, device={"datum": [1.0, 2.0, 3.0]}).datum == (1.0, 2.0, 3.0)
    with_driver = dataclasses.replace(robot, driver_params={"mavlink": {"datum": [5.0, 6.0, 7.0]}})
    assert RoverDevice(with_driver).datum == (5.0, 6.0, 7.0)
    assert RoverDevice(robot).datum is None  # ArduPilot SITL's home, as before
    with pytest.raises(DeviceError, match=r"^robot 1: mavlink device: site.datum latitude must be within"):
        RoverDevice(robot, site_datum=(91.0, 0.0, 0.0))


def test_bad_datum_settings_are_one_line_errors():
    for params, words in (({"datum": [47.0, 8.0]}, "mavlink driver: datum must be \\[lat_deg, lon_deg, alt_m\\]"),
                          ({"datum": [95.0, 8.0, 0.0]}, "mavlink driver: datum latitude must be within"),
                          ({"datum": "47,8,0"}, "mavlink driver: datum must be"),
                          ({"set_ekf_origin": True}, "mavlink driver: set_ekf_origin needs a datum"),
                          ({"set_ekf_origin": "yes", "datum": DATUM}, "mavlink driver: set_ekf_origin must be true or false")):
        with pytest.raises(ValueError, match=words) as e:
            MavlinkConfig(**params)
        assert "\n" not in str(e.value)
        with pytest.raises(ValueError, match=words):
            MavlinkDriver(1, LIMITS, **params)  # the scenario's driver settings, the same check
    assert MavlinkConfig(datum=[47, 8, 400]).datum == (47.0, 8.0, 400.0)


# --- World.lidar_at ------------------------------------------------------------------------------
def _world(robots, noise=0.0, seed=3):
    d = scenario_dict(world={"obstacles": [{"type": "cylinder", "x": 3.0, "y": 0.0, "radius": 0.5},
                                           {"type": "wall", "from": [-5, 2], "to": [5, 2], "thickness": 0.2}]},
                      robots=robots, formation={"leader": 0, "goal": [9, 0], "slots": {}}, seed=seed)
    d["robot"]["lidar"]["noise_std"] = noise
    if len(robots) > 1:
        d["formation"]["slots"] = {r["id"]: {"L": 2.0, "psi_deg": 180} for r in robots[1:]}
    return World(parse_scenario(d, "w.yaml"))


def ray_to_circle(x, y, a, cx, cy, r):
    """Analytic distance from (x, y) along heading a to the circle (cx, cy, r), or inf."""
    dx, dy = math.cos(a), math.sin(a)
    fx, fy = x - cx, y - cy
    bq = fx * dx + fy * dy
    disc = bq * bq - (fx * fx + fy * fy - r * r)
    if disc < 0:
        return math.inf
    t = -bq - math.sqrt(disc)
    return t if t > 0 else math.inf


def test_lidar_at_the_robots_own_pose_is_the_worlds_lidar():
    w = _world([{"id": 0, "role": "leader", "pose": [0, 0, 10]}, {"id": 1, "role": "follower", "pose": [1.5, -1.2, 0]}])
    try:
        for rid in (0, 1):
            i = w.index[rid]
            own = w.lidar_at(rid, (w.x[i], w.y[i], w.yaw[i]), w.beam_angles[i])
            assert np.array_equal(own, w.lidar([rid])[rid])
    finally:
        w.close()


def test_lidar_at_a_moved_pose_against_analytic_ranges():
    w = _world([{"id": 0, "role": "leader", "pose": [0, 0, 0]}, {"id": 1, "role": "follower", "pose": [-2, -1, 0]}])
    try:
        before = w.lidar()
        pos0 = p.getBasePositionAndOrientation(w.robot_bodies[0], physicsClientId=w.cid)
        angles = np.radians(np.arange(-90.0, 90.5, 2.0))
        pose = (-1.0, 0.3, math.radians(-10.0))  # behind its own body's place: that must not block
        got = w.lidar_at(0, pose, angles)
        for a, rng in zip(angles, got):
            h = pose[2] + a
            truth = min(ray_to_circle(pose[0], pose[1], h, 3.0, 0.0, 0.5),  # the cylinder
                        ray_to_circle(pose[0], pose[1], h, -2.0, -1.0, 0.5),  # robot 1
                        (1.9 - pose[1]) / math.sin(h) if math.sin(h) > 1e-9 else math.inf)  # the wall's face
            assert rng == pytest.approx(min(truth, 5.0), abs=0.01), (math.degrees(a), rng, truth)
        ahead = int(np.argmin(np.abs(pose[2] + angles)))  # the beam nearest due east hits the cylinder ~3.5 m out
        assert 3.4 < got[ahead] < 3.6
        assert p.getBasePositionAndOrientation(w.robot_bodies[0], physicsClientId=w.cid) == pos0  # put back
        after = w.lidar()
        assert all(np.array_equal(before[k], after[k]) for k in before)
        assert np.array_equal(got, w.lidar_at(0, pose, angles))  # deterministic
    finally:
        w.close()


def test_lidar_at_leaves_the_worlds_noise_stream_alone():
    robots = [{"id": 0, "role": "leader", "pose": [0, 0, 0]}]
    plain, busy = _world(robots, noise=0.02), _world(robots, noise=0.02)
    try:
        extra = [busy.lidar_at(0, (0.5 * k, 0.1, 0.2), busy.beam_angles[0][::3]) for k in range(3)]
        assert np.array_equal(plain.lidar()[0], busy.lidar()[0])  # the world's own scans as if nobody cast
        again = _world(robots, noise=0.02)
        try:
            twin = [again.lidar_at(0, (0.5 * k, 0.1, 0.2), again.beam_angles[0][::3]) for k in range(3)]
        finally:
            again.close()
        assert all(np.array_equal(a, b) for a, b in zip(extra, twin))  # same seed, same casts: same noise
        first, second = (busy.lidar_at(0, (0.0, 0.1, 0.2), busy.beam_angles[0]) for _ in range(2))
        assert not np.array_equal(first, second) and np.std(first - second) == pytest.approx(0.02 * 2 ** 0.5, rel=0.3)
    finally:
        plain.close()
        busy.close()
