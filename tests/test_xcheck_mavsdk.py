"""Cross-check of our simulated ArduPilot Rover against MAVSDK, a ground-station library we did
not write (the ``mavsdk`` wheel, 4.x: the C++ MAVSDK core as ``libcmavsdk``, in this process,
through ctypes; there is no separate ``mavsdk_server`` in 4.x).

MAVSDK connects as a ground station over UDP loopback (``udpout://`` to the rover's port, as a GCS
reaches SITL), discovers the system and identifies it, reads the flight mode through its ArduPilot
Rover mapping, arms, disarms and changes modes with its Action plugin, and gets the telemetry it
asks for (position, heading, attitude, armed state) at the rates it asks for. Every wait is
bounded; the MAVSDK instance is destroyed at the end of each test.
"""

from __future__ import annotations

import math
import threading
import time

import pytest
from mavsdk import Autopilot, ComponentType, Configuration, Mavsdk, Vehicle
from mavsdk.plugins.action import Action, ActionError
from mavsdk.plugins.info.info import Info, Version
from mavsdk.plugins.telemetry import FlightMode, Telemetry

from conftest import wait_for
from stack.sim_bridge.rover_sim import FIRMWARE, SimRover

DATUM = (47.397742, 8.545594, 488.0)  # (lat, lon, alt) of the site origin
POSE = (3.0, 4.0, 0.5)  # (x east, y north, yaw counter-clockwise from east) in our world frame
SYSTEM = 7
EARTH_RADIUS = 6_378_137.0


class Link:
    """Our rover on loopback (wall time) and a MAVSDK ground station connected to it."""

    def __init__(self):
        self.rover = SimRover(system=SYSTEM, pose=POSE, datum=DATUM).run_realtime()
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        result = self.mavsdk.add_any_connection(f"udpout://127.0.0.1:{self.rover.port}")
        assert int(result) == 0, result  # ConnectionResult.SUCCESS
        self.system = self.mavsdk.first_autopilot(20.0)  # discovery: its heartbeat, then ours seen
        assert self.system is not None, "MAVSDK found no autopilot on the rover's port"
        self.telemetry = Telemetry(self.system)
        self.action = Action(self.system)

    def close(self):
        self.mavsdk.destroy()
        self.rover.kill()


@pytest.fixture
def link():
    lk = Link()
    yield lk
    lk.close()


def test_mavsdk_discovers_and_identifies_the_rover(link):
    s = link.system
    assert s.get_system_id() == SYSTEM and s.is_connected()
    assert s.autopilot_type() == Autopilot.ARDUPILOT and s.vehicle_type() == Vehicle.ROVER
    assert s.component_ids() == [1] and s.has_autopilot()
    info = Info(s)  # AUTOPILOT_VERSION, asked for with MAV_CMD_REQUEST_MESSAGE
    version = wait_for(lambda: _try(info.get_version), 10.0, 0.2)
    assert version, "no AUTOPILOT_VERSION"
    assert (version.flight_sw_major, version.flight_sw_minor, version.flight_sw_patch) == FIRMWARE
    assert version.flight_sw_version_type == Version.FlightSoftwareVersionType.RELEASE
    ident = info.get_identification()
    assert bytes.fromhex(ident.hardware_uid).rstrip(b"\0") == f"SIMROVER{SYSTEM:03d}".encode()
    # the rover heard MAVSDK as a ground station: its heartbeats, from its own system id
    gcs = [m for _, m in list(link.rover.rx_log) if m.get_type() == "HEARTBEAT"]
    assert gcs and gcs[0].type == 6 and gcs[0].get_srcSystem() != SYSTEM  # MAV_TYPE_GCS
    assert not {k for k in link.rover.counters if k in ("bad_data", "unknown_msg", "truncated", "not_for_us")}


def test_mavsdk_reads_modes_arms_disarms_and_sets_modes(link):
    tel, act, rover = link.telemetry, link.action, link.rover

    def mode_is(mode):
        return wait_for(lambda: tel.flight_mode() == mode, 4.0, 0.05)

    assert mode_is(FlightMode.HOLD) and not tel.armed()  # boots in HOLD, disarmed
    # MAVSDK's ArduPilot Rover mapping of our HEARTBEAT custom_mode
    for ours, theirs in (("GUIDED", FlightMode.OFFBOARD), ("MANUAL", FlightMode.MANUAL), ("AUTO", FlightMode.MISSION),
                         ("RTL", FlightMode.RETURN_TO_LAUNCH), ("HOLD", FlightMode.HOLD)):
        rover.force_mode(ours)
        assert mode_is(theirs), (ours, tel.flight_mode())

    act.arm()  # COMMAND_LONG ARM_DISARM, our ACK
    assert rover.armed and wait_for(tel.armed, 4.0, 0.05)
    act.return_to_launch()  # MAVSDK sets Rover's RTL mode (DO_SET_MODE, custom mode 11)
    assert rover.mode_name == "RTL" and mode_is(FlightMode.RETURN_TO_LAUNCH)
    act.hold()
    assert rover.mode_name == "HOLD" and mode_is(FlightMode.HOLD)
    act.disarm()
    assert not rover.armed and wait_for(lambda: not tel.armed(), 4.0, 0.05)

    rover.arming_check_failed = True  # a failed pre-arm check: MAVSDK gets the refusal
    with pytest.raises(ActionError, match="DENIED"):
        act.arm()
    assert not rover.armed


def test_mavsdk_gets_the_telemetry_it_asks_for_at_its_rates(link):
    tel, rover = link.telemetry, link.rover
    tel.set_rate_position(5.0)  # MAV_CMD_SET_MESSAGE_INTERVAL: GLOBAL_POSITION_INT
    tel.set_rate_attitude_euler(10.0)  # ATTITUDE
    arrivals: dict[str, list[float]] = {"position": [], "attitude": [], "heading": []}
    latest: dict[str, object] = {}
    lock = threading.Lock()

    def on(kind):
        def cb(value, _user):
            with lock:
                arrivals[kind].append(time.monotonic())
                latest[kind] = value
        return cb
    tel.subscribe_position(on("position"))
    tel.subscribe_attitude_euler(on("attitude"))
    tel.subscribe_heading(on("heading"))
    assert wait_for(lambda: all(arrivals.values()), 5.0), arrivals
    time.sleep(0.5)  # past the first burst
    with lock:
        for v in arrivals.values():
            v.clear()
    time.sleep(3.0)
    with lock:
        rates = {k: len(v) / 3.0 for k, v in arrivals.items()}
        pos, att, hdg = latest["position"], latest["attitude"], latest["heading"]
    assert 4.0 <= rates["position"] <= 6.0 and 8.0 <= rates["attitude"] <= 12.0, rates
    assert 4.0 <= rates["heading"] <= 6.0, rates  # from GLOBAL_POSITION_INT's hdg

    # the values, against a tangent plane computed here (north = y, east = x)
    lat = DATUM[0] + math.degrees(POSE[1] / EARTH_RADIUS)
    lon = DATUM[1] + math.degrees(POSE[0] / (EARTH_RADIUS * math.cos(math.radians(DATUM[0]))))
    assert pos.latitude_deg == pytest.approx(lat, abs=2e-7) and pos.longitude_deg == pytest.approx(lon, abs=2e-7)
    assert pos.absolute_altitude_m == pytest.approx(DATUM[2], abs=0.01) and pos.relative_altitude_m == pytest.approx(0.0)
    heading_deg = 90.0 - math.degrees(POSE[2])  # compass: clockwise from north
    assert hdg.heading_deg == pytest.approx(heading_deg, abs=0.01)
    assert att.yaw_deg == pytest.approx(heading_deg, abs=0.01) and att.roll_deg == 0.0 and att.pitch_deg == 0.0

    tel.set_rate_position(10.0)  # a new rate, and the rover follows it
    assert rover.intervals[33] == pytest.approx(0.1)  # GLOBAL_POSITION_INT
    rover.set_pose(-20.0, 10.0, math.pi)  # the world moved it: facing west
    assert wait_for(lambda: latest["heading"].heading_deg == pytest.approx(270.0, abs=0.01), 3.0)
    lat = DATUM[0] + math.degrees(10.0 / EARTH_RADIUS)
    assert wait_for(lambda: latest["position"].latitude_deg == pytest.approx(lat, abs=2e-7), 3.0)
    with lock:
        arrivals["position"].clear()
    time.sleep(2.0)
    with lock:
        assert 8.0 <= len(arrivals["position"]) / 2.0 <= 12.0, len(arrivals["position"])


def _try(fn):
    try:
        return fn()
    except Exception:  # InfoError until AUTOPILOT_VERSION came
        return None
