"""A robot's own file over the fleet's mission file, and ``stack-agent --check`` against simulated robots.

The robots are the world's hosted devices (``stack.sim_bridge``: a hardware-like Jackal whose clock is 3.7 s
ahead and whose lidar runs at 15 Hz, an ODrive pair on an slcan pty, an ArduPilot rover on UDP), in a
real-time world that steps because this test holds each robot's liveliness token (no agent commands them). The
check is ``stack-agent --check`` as a process, with ``--robot`` files that say where each device is, as a
robot's own file says on hardware.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from conftest import ROOT, run_cli, wait_port
from stack.robotfile import layer, load_mission
from stack.scenario import ScenarioError, parse_scenario

FLEET = "checkf"
JACKAL = {"driver": "jackal", "device": {"jackal": {"clock_offset_s": 3.7, "lidar_rate_hz": 15.0}}}
CAN = {"driver": "can", "policy": "aina"}
ROVER = {"driver": "mavlink"}
CAN_RPLIDAR = {"driver": "can", "policy": "aina", "lidar": {"source": "rplidar"}}  # its own RPLidar A1 on a pty
KINDS = {0: JACKAL, 1: CAN, 2: ROVER, 3: CAN_RPLIDAR}


def mission() -> dict:
    """A fleet's mission: no ``world:``, no ``success:`` (those are the simulation's)."""
    return {
        "name": "check-mission", "seed": 1, "dt": 0.1, "duration": 600.0,
        "site": {"datum": [47.397742, 8.545594, 488.0]},
        "robot": {"radius": 0.4, "lidar": {"beams": 90, "fov_deg": 180, "range": 6.0}},
        "formation": {"leader": 0, "goal": [40.0, -1.0], "slots": {1: {"L": 3.0, "psi_deg": 150},
                                                                   2: {"L": 3.0, "psi_deg": -150},
                                                                   3: {"L": 6.0, "psi_deg": 180}}},
        "robots": [{"id": 0, "pose": [2.0, -1.0, 30.0]}, {"id": 1, "pose": [-1.0, 1.0, 0.0]},
                   {"id": 2, "pose": [-1.0, -3.0, 0.0]}, {"id": 3, "pose": [-4.0, -1.0, 0.0]}],
    }


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """Router + real-time world hosting each robot's device; yields (endpoint, mission path, devices, folder)."""
    from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session
    from stack.comm import Keys

    tmp = tmp_path_factory.mktemp("check")
    (tmp / "mission.yaml").write_text(yaml.safe_dump(mission(), sort_keys=False))
    raw = mission()
    for rid, kind in KINDS.items():  # the world hosts the device each robot's own file names
        raw = layer(raw, rid, kind)
    (tmp / "world.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
    ep = free_tcp_endpoint()
    procs = [subprocess.Popen([sys.executable, "-m", "stack.comm.router", "--listen", ep], cwd=ROOT,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    tokens, session = [], None
    try:
        wait_port(ep)
        procs.append(subprocess.Popen([sys.executable, "-m", "stack.sim_bridge", "--scenario", str(tmp / "world.yaml"),
                                       "--connect", ep, "--fleet", FLEET, "--out", str(tmp / "out"), "--realtime",
                                       "--wait-agents", "300"], cwd=ROOT, stdout=subprocess.DEVNULL,
                                      stderr=open(tmp / "world.log", "w")))
        devices = _devices(tmp / "out" / "devices.json", procs[-1])
        session = open_session(SessionConfig(mode="client", connect=[ep]))
        tokens = [session.liveliness().declare_token(Keys(FLEET).alive(rid)) for rid in KINDS]  # the world steps
        yield ep, tmp / "mission.yaml", devices, tmp
    finally:
        for t in tokens:
            t.undeclare()
        if session is not None:
            session.close()
        for p in reversed(procs):
            p.terminate()
            p.wait(20)


def _devices(path: Path, world: subprocess.Popen, timeout: float = 120.0) -> dict[int, dict]:
    end = time.monotonic() + timeout
    while not path.exists():
        assert world.poll() is None and time.monotonic() < end, "the world did not bring its devices up"
        time.sleep(0.1)
    return {int(k): v["settings"] for k, v in json.loads(path.read_text()).items()}


def _robot_file(tmp: Path, name: str, data: dict) -> Path:
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _check(ep: str, mission_path: Path, rid: int, robot_file: Path, *extra: str) -> subprocess.CompletedProcess:
    return run_cli(["stack-agent", "--id", str(rid), "--scenario", str(mission_path), "--robot", str(robot_file),
                    "--connect", ep, "--fleet", FLEET, "--check", "--check-duration", "2", *extra], timeout=180)


def _row(stdout: str, item: str) -> str:
    (line,) = [ln for ln in stdout.splitlines() if ln.strip().startswith(item + "  ")]
    return line


@pytest.mark.fleet
def test_check_reads_a_robots_own_rplidar(site):
    """A CAN base with its own RPLidar A1 (the world's simulated one on a pty, 5.5 Hz, 360 degrees): the check
    opens the sensor driver, sees its rate and its beams, and says ready."""
    ep, mission_path, devices, tmp = site
    lidar = json.loads((tmp / "out" / "devices.json").read_text())["3"]["lidar"]["settings"]
    own = CAN_RPLIDAR | {"can": devices[3], "lidar": {"source": "rplidar", "rplidar": lidar}}
    p = _check(ep, mission_path, 3, _robot_file(tmp, "ok-3", own))
    assert p.returncode == 0 and "result: ready" in p.stdout, p.stdout + p.stderr
    row = _row(p.stdout, "lidar")
    assert " ok " in row and "lidar source rplidar" in row, row
    assert float(row.split(": ")[1].split(" Hz")[0]) == pytest.approx(5.5, rel=0.3), row
    beams = int(row.split("; ")[1].split(" beams")[0])
    assert 250 < beams < 450, row  # about 2000 samples/s at 5.5 rev/s, less the invalid ones


@pytest.mark.fleet
@pytest.mark.parametrize("rid", [0, 1, 2], ids=["jackal", "can", "mavlink"])
def test_check_of_a_healthy_robot_says_ready_and_what_it_sees(site, rid):
    ep, mission_path, devices, tmp = site
    kind = KINDS[rid]
    own = dict(kind) | {kind["driver"]: devices[rid]}  # where its device is: what a robot's own file says
    log = tmp / f"check-{rid}.asc"
    p = _check(ep, mission_path, rid, _robot_file(tmp, f"ok-{rid}", own), *(["--can-log", str(log)] if rid == 1 else []))
    assert p.returncode == 0, p.stdout + p.stderr
    assert "result: ready" in p.stdout and p.stderr == "", p.stdout + p.stderr
    assert "its host's clock" in _row(p.stdout, "router") and "ms from ours" in _row(p.stdout, "router")
    odom, lidar = _row(p.stdout, "odometry"), _row(p.stdout, "lidar")
    assert " ok " in odom and " ok " in lidar
    hz = {0: 50.0, 1: 100.0, 2: 10.0}[rid]  # Jackal EKF 50 Hz, ODrive encoders 100 Hz, rover position 10 Hz
    assert float(odom.split(": ")[1].split(" Hz")[0]) == pytest.approx(hz, rel=0.5), odom
    lidar_hz = float(lidar.split(": ")[1].split(" Hz")[0])
    assert lidar_hz == pytest.approx(15.0 if rid == 0 else 10.0, rel=0.5), lidar
    if rid == 0:  # the Jackal's own LaserScan, its clock 3.7 s ahead, odometry from where it booted
        assert "jackal driver's own scan" in lidar
        offset = float(_row(p.stdout, "odom clock").split("device stamps ")[1].split(" s")[0])
        assert offset == pytest.approx(3.7, abs=0.15)
        assert "odom_origin boot" in _row(p.stdout, "odom frame") and "is site (2.00, -1.00, 30 deg)" in p.stdout
    else:
        assert "lidar source world" in lidar and f"stack/{FLEET}/{rid}/scan" in lidar
        assert "stamped by the driver on arrival" in _row(p.stdout, "odom clock")
    if rid == 1:  # what went on the bus: closed loop at zero, nothing but zero, IDLE at the end
        sent = _sent_frames(log)
        assert sent["Set_Input_Vel"] and set(sent["Set_Input_Vel"]) == {0.0}, sent
        assert sent["Set_Axis_State"][:2] == [8, 8] and sent["Set_Axis_State"][-2:] == [1, 1], sent
    if rid == 2:  # the autopilot's own position
        assert "mavlink driver's own position" in _row(p.stdout, "driver fixes")


def _sent_frames(path: Path) -> dict[str, list[float]]:
    """The check's own frames in a CAN log: each Set_Input_Vel's velocity, each Set_Axis_State's state."""
    import can

    from stack.drivers import odrive

    out: dict[str, list[float]] = {"Set_Input_Vel": [], "Set_Axis_State": []}
    for m in can.LogReader(str(path)):
        if m.is_remote_frame or m.is_error_frame:
            continue
        f = odrive.decode(m, None)
        if f.name == "Set_Input_Vel":
            out[f.name].append(f.signals["Input_Vel"])
        elif f.name == "Set_Axis_State":
            out[f.name].append(f.signals["Axis_Requested_State"])
    return out


@pytest.mark.fleet
def test_check_of_a_broken_robot_names_each_missing_thing(site):
    ep, mission_path, devices, tmp = site
    # a CAN bus where no ODrive answers: the driver does not open (and its lidar is not there either: other fleet)
    dead_bus = CAN | {"can": {"interface": "virtual", "channel": "check-nobody", "open_timeout": 0.3}}
    p = _check(ep, mission_path, 1, _robot_file(tmp, "dead", dead_bus), "--fleet", "nobody")
    assert p.returncode == 1, p.stdout + p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 2 and "result: 2 missing" in p.stdout, p.stderr
    assert lines[0].startswith("stack-agent --check: robot 1: driver: can:") and "no heartbeat" in lines[0]
    assert lines[1].startswith("stack-agent --check: robot 1: lidar: nothing from lidar source world")
    assert "the aina policy reads it" in lines[1]
    # the real ODrive pair, but no lidar where the policy needs one: odometry fine, lidar named
    p = _check(ep, mission_path, 1, _robot_file(tmp, "nolidar", CAN | {"can": devices[1]}), "--fleet", "nobody")
    assert p.returncode == 1, p.stdout + p.stderr
    assert " ok " in _row(p.stdout, "odometry") and " ok " in _row(p.stdout, "driver")
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "lidar: nothing from lidar source world (the simulated world's lidar, on stack/nobody/1/scan)" in p.stderr


def test_a_bad_robot_file_is_one_line_exit_2(tmp_path, capsys):
    from stack.agents.cli import cli

    path = tmp_path / "mission.yaml"
    path.write_text(yaml.safe_dump(mission(), sort_keys=False))
    argv = ["--id", "1", "--scenario", str(path), "--robot", str(tmp_path / "bad.yaml"), "--check"]
    _robot_file(tmp_path, "bad", {"bogus": 1})
    p = run_cli(["stack-agent", *argv], timeout=120)  # as a process: exit 2, one line
    assert p.returncode == 2 and p.stderr.strip().splitlines() == [p.stderr.strip()], p.stderr
    assert "bad.yaml: bogus: unknown field (allowed: " in p.stderr, p.stderr
    cases = {"nested": ({"driver": "can", "can": {"chanel": "can0"}}, "bad.yaml: can.chanel: unknown field"),
             "value": ({"lidar": {"beams": 0}}, "bad.yaml: lidar.beams: must be >= 1, got 0"),
             "device": ({"driver": "can", "device": {"can": {"power_up_pos_rev": 3}}}, "bad.yaml: device.can: "),
             "id": ({"id": 2}, "bad.yaml: id: 2, but this robot is --id 1"),
             "layered": ({"role": "leader"}, "bad.yaml: over "),
             "yaml": ("a: [1,", "bad.yaml: line 1, column "),
             "missing": (None, "bad.yaml: cannot read")}
    for name, (data, want) in cases.items():
        bad = tmp_path / "bad.yaml"
        if data is None:
            bad.unlink()
        else:
            bad.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
        assert cli(argv) == 2, name
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and want in err, (name, err)


def test_the_robot_file_is_layered_over_its_entry_and_the_mission_defaults(tmp_path):
    path = tmp_path / "mission.yaml"
    raw = mission()
    raw["robots"][1] |= {"driver": "can", "can": {"node_left": 4, "node_right": 5}, "lidar": {"range": 4.0}}
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    own = _robot_file(tmp_path, "own", {"can": {"channel": "can1"}, "lidar": {"beams": 30}, "pose": [0.5, 0.5, 90],
                                        "odom_origin": "first", "v_max": 0.5})
    sc = load_mission(path, 1, own)
    r = sc.robot(1)
    assert r.driver == "can" and r.driver_params["can"] == {"node_left": 4, "node_right": 5, "channel": "can1"}
    assert (r.lidar.beams, r.lidar.range, r.lidar.fov) == (30, 4.0, pytest.approx(3.14159, abs=1e-4))  # 3 layers
    assert r.pose == pytest.approx((0.5, 0.5, 1.5707963)) and r.odom_origin == "first" and r.v_max == 0.5
    assert sc.robot(2) == load_mission(path, 2).robot(2)  # the others as the mission says
    assert sc.obstacles == () and sc.success.max_time is None  # world: and success: are the simulation's
    with pytest.raises(ScenarioError, match="the mission has no robot with id 7"):
        layer(raw, 7, {})


def test_every_example_robot_file_in_deploy_parses_over_the_mission():
    deploy = ROOT / "deploy" / "robots"
    files = sorted(deploy.glob("*/robot.yaml"))
    assert {f.parent.name for f in files} == {"jackal", "can-base", "ardupilot-rover"}
    drivers = set()
    for f in files:
        rid = yaml.safe_load(f.read_text())["id"]
        r = load_mission(deploy / "mission.yaml", rid, f).robot(rid)
        drivers.add(r.driver)
        assert (f.parent / "README.md").exists()
    assert drivers == {"jackal", "can", "mavlink"}
    parse_scenario(yaml.safe_load((deploy / "mission.yaml").read_text()), "mission.yaml")


@pytest.mark.fleet
def test_a_robot_file_over_a_mission_without_world_or_success_runs(site):
    """A bounded real run (``--steps``) of the Jackal from the mission and its own file."""
    ep, mission_path, devices, tmp = site
    own = _robot_file(tmp, "run-0", JACKAL | {"jackal": devices[0]})
    p = run_cli(["stack-agent", "--id", "0", "--role", "leader", "--scenario", str(mission_path), "--robot", str(own),
                 "--connect", ep, "--fleet", FLEET, "--steps", "5", "--log-level", "INFO"], timeout=180)
    assert p.returncode == 0, p.stderr[-3000:]
    resolved = [ln for ln in p.stderr.splitlines() if "agent 0 resolved" in ln]
    assert len(resolved) == 1 and "driver jackal" in resolved[0] and "odom_origin boot" in resolved[0], resolved


@pytest.mark.parametrize("stamping", [True, False], ids=["router stamps", "timestamping off"])
def test_the_router_clock_probe_measures_only_what_the_router_stamped(stamping):
    from stack.comm.clockprobe import ClockOffset, router_offset
    from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session

    ep = free_tcp_endpoint()
    over = {} if stamping else {"timestamping/enabled": '{"router": false, "peer": false, "client": false}'}
    client = SessionConfig(mode="client", connect=[ep])
    with open_session(SessionConfig(mode="router", listen=[ep], overrides=over)), open_session(client) as s:
        got = router_offset(s, client, "stack/probe-test/0/check", probes=5, timeout_s=5.0)
    if stamping:  # the router runs on this host, on this clock: within the probe's own bound (and a little)
        assert isinstance(got, ClockOffset) and got.probes >= 5, got
        assert abs(got.offset_s) <= got.bound_s + 0.002 and got.bound_s < 0.5, got
    else:
        assert got == "not measured: the router does not timestamp what it routes (its timestamping is off)"


def test_the_odom_frame_row_warns_where_odom_origin_puts_the_robot_away_from_its_start():
    from dataclasses import replace

    from stack.agents.check import _frame_text

    sc = parse_scenario(mission(), "m.yaml")
    booted = replace(sc.robot(0), odom_origin="boot")  # start (2, -1, 30 deg)
    assert _frame_text(booted, (0.0, 0.0, 0.0))[0] == "info"
    state, text = _frame_text(replace(booted, odom_origin="site"), (0.0, 0.0, 0.0))  # told odom is the site's
    assert state == "warn" and "is site (0.00, 0.00, 0 deg)" in text and "2.2 m apart" in text, text
    assert _frame_text(replace(booted, odom_origin="first"), (5.0, 5.0, 1.0))[0] == "info"
