"""The simulated ArduPilot Rover as a ground station sees it, with hardware-like settings.

The ground station is pymavlink's own ``mavutil`` connection (its flight-mode decoding, its
parser), not our driver; the rover is the world's ``RoverDevice`` stepped in lock-step sim
time. Geodesy is checked with pymavlink's ``mavextra.gps_offset``, not our tangent plane.
"""

from __future__ import annotations

import math
import time

import pytest
from pymavlink import mavextra, mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from stack.scenario import RobotConfig
from stack.sim_bridge.devices import Body, DeviceError
from stack.sim_bridge.devices_mavlink import RoverDevice, RoverDeviceConfig

BOOT = (3.0, -2.0, math.radians(30.0))
DATUM = (47.3977, 8.5456, 408.0)
DT = 0.1
TYPE_MASK_YAW_RATE_ONLY = 1535  # NOTES.md / ArduPilot Rover docs
TYPE_MASK_VEL_YAW_RATE = 1511
TYPE_MASK_POSITION = 3580


class Station:
    """A ground station on the rover's link: pymavlink's mavutil, and the rover stepped by hand."""

    def __init__(self, **settings):
        robot = RobotConfig(id=1, role="leader", pose=BOOT, driver="mavlink",
                            driver_params={"mavlink": {"position_std": 1e-9}})
        self.dev = RoverDevice(robot, device={"ideal": False, "datum": list(DATUM), **settings})
        self.dev.start()
        self.dev.lockstep(0.0)
        self.gs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{self.dev.rover.port}", source_system=255,
                                             source_component=190, dialect="ardupilotmega")
        self.t = 0.0
        self.body = Body(*BOOT, 0.0, 0.0)
        self.got: list = []
        self.step(1)

    def step(self, n: int = 1, move=None) -> list:
        """n world steps; ``move(body, t) -> body`` moves the body (default: the rover's own speeds, held)."""
        out = []
        for _ in range(n):
            if round(self.t * 10) % 10 == 0:  # a GCS heartbeat every second (the rover's FS_GCS watches it)
                self.gs.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            time.sleep(0.01)  # loopback UDP: what the station sent is in the rover's socket
            self.dev.take_commands(self.t)
            v, w = self.dev.motion(self.t + DT)
            x, y, yaw = self.body.x, self.body.y, self.body.yaw
            self.body = Body(x + v * DT * math.cos(yaw), y + v * DT * math.sin(yaw), yaw + w * DT, v, w)
            if move is not None:
                self.body = move(self.body, self.t + DT)
            self.t = round(self.t + DT, 9)
            self.dev.report(self.t, self.body)
            out += self.drain()
        return out

    def drain(self) -> list:
        time.sleep(0.01)
        out = []
        while (m := self.gs.recv_msg()) is not None:
            if m.get_type() != "BAD_DATA":
                out.append(m)
        self.got += out
        return out

    def command(self, cmd: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.gs.mav.command_long_send(1, 1, cmd, 0, *p)

    def close(self) -> None:
        self.gs.close()
        self.dev.close()


def of(msgs, kind: str) -> list:
    return [m for m in msgs if m.get_type() == kind]


@pytest.fixture
def station():
    s = Station()
    yield s
    s.close()


def site_of(lat_e7: int, lon_e7: int) -> tuple[float, float]:
    """Site (x east, y north) of a GLOBAL_POSITION_INT fix, through pymavlink's gps_offset around the datum."""
    lat1, lon1 = mavextra.gps_offset(DATUM[0], DATUM[1], 0.0, 1.0)  # one metre north
    lat2, lon2 = mavextra.gps_offset(DATUM[0], DATUM[1], 1.0, 0.0)  # one metre east
    return (lon_e7 * 1e-7 - DATUM[1]) / (lon2 - DATUM[1]), (lat_e7 * 1e-7 - DATUM[0]) / (lat1 - DATUM[0])


def test_telemetry_only_when_asked_then_at_the_stream_rate(station):
    quiet = station.step(10)
    assert not of(quiet, "LOCAL_POSITION_NED") and not of(quiet, "GLOBAL_POSITION_INT") and not of(quiet, "ATTITUDE")
    assert len(of(quiet, "HEARTBEAT")) == 1  # 1 Hz, unasked
    station.gs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_POSITION, 5, 1)
    station.step(1)  # the stream starts
    got = station.step(10)
    assert len(of(got, "GLOBAL_POSITION_INT")) == 5 and len(of(got, "LOCAL_POSITION_NED")) == 5  # 5 Hz over 1 s
    assert not of(got, "ATTITUDE") and not of(got, "COMMAND_ACK")  # another group; a message is not ACKed
    station.gs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_ALL, 10, 1)
    station.step(1)
    got = station.step(10)
    assert len(of(got, "ATTITUDE")) == 10 and len(of(got, "SYS_STATUS")) == 10
    station.gs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_ALL, 0, 0)  # stop
    station.step(1)
    assert not of(station.step(10), "LOCAL_POSITION_NED")


def test_message_interval_and_request_message_are_acked(station):
    station.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 200_000)  # 5 Hz
    acks = of(station.step(1), "COMMAND_ACK")
    got = station.step(10)
    assert [(a.command, a.result) for a in acks] == [(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAV_RESULT_ACCEPTED)]
    assert len(of(got, "ATTITUDE")) == 5
    station.command(mav.MAV_CMD_GET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE)
    got = station.step(1)
    assert of(got, "MESSAGE_INTERVAL")[0].interval_us == 200_000
    station.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
    station.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_BATTERY_STATUS)  # not a message it has
    got = station.step(1)
    assert [(a.command, a.result) for a in of(got, "COMMAND_ACK")] == [
        (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_RESULT_ACCEPTED), (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_RESULT_FAILED)]
    kinds = [m.get_type() for m in got if m.get_type() in ("COMMAND_ACK", "GLOBAL_POSITION_INT")]
    assert kinds[:2] == ["COMMAND_ACK", "GLOBAL_POSITION_INT"]  # the ACK, then the message, once
    assert len(of(got, "GLOBAL_POSITION_INT")) == 1


def test_heartbeat_flags_and_system_status_as_rover(station):
    hb = of(station.step(10), "HEARTBEAT")[-1]
    assert station.gs.flightmode == "HOLD" and hb.type == mav.MAV_TYPE_GROUND_ROVER
    assert hb.system_status == mav.MAV_STATE_STANDBY and not hb.base_mode & mav.MAV_MODE_FLAG_GUIDED_ENABLED
    station.gs.set_mode("GUIDED")  # mavutil's own mode mapping for a rover
    station.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    hb = of(station.step(10), "HEARTBEAT")[-1]
    assert station.gs.flightmode == "GUIDED" and station.gs.motors_armed()
    assert hb.base_mode & mav.MAV_MODE_FLAG_GUIDED_ENABLED and hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.system_status == mav.MAV_STATE_ACTIVE
    station.gs.set_mode("MANUAL")
    hb = of(station.step(10), "HEARTBEAT")[-1]
    assert hb.base_mode & mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED and not hb.base_mode & mav.MAV_MODE_FLAG_GUIDED_ENABLED
    assert hb.system_status == mav.MAV_STATE_ACTIVE  # armed or not, only HOLD is STANDBY


def test_ekf_origin_at_boot_and_global_position_around_the_datum(station):
    station.gs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_POSITION, 10, 1)
    got = station.step(2)
    local = of(got, "LOCAL_POSITION_NED")[-1]
    assert (local.x, local.y) == pytest.approx((0.0, 0.0), abs=1e-6)  # booted here: the EKF origin
    g = of(got, "GLOBAL_POSITION_INT")[-1]
    assert site_of(g.lat, g.lon) == pytest.approx(BOOT[:2], abs=0.02)
    assert g.alt == 408_000 and g.relative_alt == 0 and g.hdg == 6000  # 30 deg ccw from east: 60 deg from north

    def to(x, y):
        return lambda body, t: Body(x, y, math.radians(90.0), 0.5, 0.0)

    got = station.step(2, move=to(5.0, 1.0))
    local, g = of(got, "LOCAL_POSITION_NED")[-1], of(got, "GLOBAL_POSITION_INT")[-1]
    assert (local.x, local.y) == pytest.approx((3.0, 2.0), abs=1e-3)  # north, east of the boot point
    assert site_of(g.lat, g.lon) == pytest.approx((5.0, 1.0), abs=0.02)
    assert (g.vx, g.vy, g.hdg) == (50, 0, 0)  # 0.5 m/s due north
    lat, lon, alt = int(DATUM[0] * 1e7), int(DATUM[1] * 1e7), int(DATUM[2] * 1e3)
    station.gs.mav.set_gps_global_origin_send(1, lat, lon, alt)
    got = station.step(2, move=to(5.0, 1.0))
    origin = of(got, "GPS_GLOBAL_ORIGIN")[0]
    assert (origin.latitude, origin.longitude, origin.altitude) == (lat, lon, alt)
    local = of(got, "LOCAL_POSITION_NED")[-1]
    assert (local.x, local.y) == pytest.approx((1.0, 5.0), abs=0.02)  # the site frame, now in NED


def test_type_masks_as_rover_reads_them(station):
    station.gs.set_mode("GUIDED")
    station.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    station.step(2)

    def target(mask, frame=mav.MAV_FRAME_BODY_NED, x=0.0, y=0.0, vx=0.0, yaw_rate=0.0):
        station.gs.mav.set_position_target_local_ned_send(0, 1, 1, frame, mask, x, y, 0, vx, 0, 0, 0, 0, 0, 0, yaw_rate)

    target(TYPE_MASK_YAW_RATE_ONLY, vx=1.0, yaw_rate=0.5)  # vx is ignored: turn on the spot, clockwise (NED)
    station.step(20)
    assert station.dev.rover.body_velocity() == pytest.approx((0.0, -0.5), abs=1e-6)
    target(TYPE_MASK_VEL_YAW_RATE & ~(1 << 6), vx=0.2)  # ax used, ay ignored: any bit ignores the group (defines.h)
    station.step(20)
    assert station.dev.rover.body_velocity() == pytest.approx((0.2, 0.0), abs=1e-6)
    target(TYPE_MASK_VEL_YAW_RATE & ~0xC0, vx=1.0)  # ax and ay both used: rejected, said so
    got = station.step(1)
    assert any(m.text.startswith("Ignoring SET_POSITION_TARGET_LOCAL_NED") for m in of(got, "STATUSTEXT"))  # 50 chars, as AP
    assert station.dev.rover.counters["target_accel_rejected"] == 1
    target(TYPE_MASK_VEL_YAW_RATE, vx=-0.4, yaw_rate=0.0)  # reverse
    station.step(20)
    assert station.dev.rover.body_velocity() == pytest.approx((-0.4, 0.0), abs=1e-6)
    target(TYPE_MASK_POSITION, frame=mav.MAV_FRAME_LOCAL_NED, x=0.0, y=6.0)  # 6 m east of the EKF origin (boot)
    station.step(150)
    x, y = station.body.x, station.body.y
    assert math.hypot(x - (BOOT[0] + 6.0), y - BOOT[1]) <= 2.0 + 0.3  # stopped within WP_RADIUS (2 m)
    assert station.dev.rover.body_velocity() == pytest.approx((0.0, 0.0), abs=1e-6)
    assert station.dev.rover.counters.get("target_timeout", 0) == 0  # position targets do not time out


def test_bad_settings_name_the_field():
    robot = RobotConfig(id=1, role="leader", pose=BOOT, driver="mavlink")
    for settings, field in (({"ekf_origin": "gps"}, "ekf_origin"), ({"datum": [1.0, 2.0]}, "datum"),
                            ({"datum": [95.0, 0.0, 0.0]}, "datum latitude"), ({"origin": 1}, "origin")):
        with pytest.raises(DeviceError, match=f"robot 1: mavlink device: .*{field}"):
            RoverDevice(robot, device=settings)
    assert not RoverDeviceConfig().ideal and RoverDeviceConfig(datum=[1, 2, 3]).datum == (1.0, 2.0, 3.0)


def test_ideal_keeps_the_site_origin_as_the_ekf_origin():
    robot = RobotConfig(id=1, role="leader", pose=BOOT, driver="mavlink")
    dev = RoverDevice(robot, device={"ideal": True})
    dev.start()
    try:
        assert dev.rover.origin == dev.rover.datum and dev.rover.datum[:2] == (-35.363261, 149.165230)
    finally:
        dev.close()
