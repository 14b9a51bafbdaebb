"""Mixed reality: a real robot (here a hardware-like Jackal in a stand-in site, ``stack.fleet.mixed.Site``, a world
process the fleet's world does not know) and simulated robots in one fleet, each seeing the other."""

from __future__ import annotations

import copy
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import ROOT, run_cli, wait_for, wait_port, write_scenario

from stack.comm.session import free_tcp_endpoint
from stack.fleet.mixed import Site, reality_scenario, run_mixed, site_namespace
from stack.scenario import ScenarioError, parse_scenario
from stack.viz.messages import TOPICS

pytestmark = pytest.mark.fleet

MOCAP_KEY = "vrpn_mocap/site_robot0/pose"
REAL = {"embodiment": "real", "driver": "jackal", "jackal": {"namespace": site_namespace(0)}}


def mixed_diamond() -> dict:
    """A real leader (a Jackal, its lidar merged with the virtual robots) and three simulated followers."""
    return {
        "name": "mixed-diamond", "seed": 3, "dt": 0.1, "duration": 30.0,
        "world": {"obstacles": [{"type": "wall", "from": [-6, 6], "to": [12, 6], "thickness": 0.2},
                                {"type": "cylinder", "x": 4.0, "y": -4.0, "radius": 0.5, "virtual": True}]},
        "robot": {"radius": 0.3, "v_max": 0.8, "w_max": 1.5, "comm_range": 15.0,
                  "lidar": {"beams": 180, "fov_deg": 180, "range": 5.0}},
        "formation": {"leader": 0, "goal": [7.0, -0.5],
                      "slots": {1: {"L": 2.0, "psi_deg": 135}, 2: {"L": 2.0, "psi_deg": 180},
                                3: {"L": 2.0, "psi_deg": -135}}},
        # booted away from the site origin: its odometry is (0, 0, 0) at (1.0, -0.5, 20 deg)
        "robots": [{"id": 0, "role": "leader", "pose": [1.0, -0.5, 20.0], **REAL, "lidar": {"virtual": True}},
                   {"id": 1, "role": "follower", "pose": [-1.4, 1.4, 0.0]},
                   {"id": 2, "role": "follower", "pose": [-2.0, 0.0, 0.0]},
                   {"id": 3, "role": "follower", "pose": [-1.4, -1.4, 0.0]}],
        "success": {"goal_tolerance": 0.4, "max_time": 30.0, "no_collisions": True},
    }


def parked(virtual: bool) -> dict:
    """A real robot driving at a simulated one parked across its path (nothing in the site itself)."""
    return {
        "name": "parked", "seed": 1, "dt": 0.1, "duration": 60.0, "coordination": "arrival_time",
        "robot": {"radius": 0.3, "v_max": 0.6, "w_max": 1.5, "comm_range": 15.0,
                  "lidar": {"beams": 90, "fov_deg": 180, "range": 4.0}},
        "robots": [{"id": 0, "pose": [0.0, 0.0, 0.0], "goal": [6.0, 0.0], **REAL, "lidar": {"virtual": virtual}},
                   {"id": 1, "pose": [2.2, 0.0, 90.0], "goal": [2.2, 0.0]}],
    }


def _popen(args: list[str], log: Path) -> subprocess.Popen:
    mod = {"stack-fleet": "stack.fleet", "stack-agent": "stack.agents", "stack-world": "stack.sim_bridge",
           "stack-router": "stack.comm.router"}[args[0]]
    return subprocess.Popen([sys.executable, "-m", mod, *args[1:]], cwd=ROOT, stdout=log.open("w"),
                            stderr=subprocess.STDOUT, env={**__import__("os").environ, "PYTHONUNBUFFERED": "1"})


def _stop(p: subprocess.Popen, sig=signal.SIGTERM) -> None:
    if p.poll() is None:
        p.send_signal(sig)
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _records(path: Path) -> list[dict]:
    """The real robot's step log, each record with its scan (``scan_same`` filled in)."""
    out, scan = [], None
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        scan = scan if rec.get("scan_same") else rec.get("scan")
        rec["scan"] = scan
        out.append(rec)
    return out


@pytest.fixture
def router(tmp_path):
    ep = free_tcp_endpoint()
    p = _popen(["stack-router", "--listen", ep], tmp_path / "router.log")
    wait_port(ep)
    yield ep
    _stop(p)


def test_a_real_jackal_and_three_simulated_robots_finish_the_formation_judged_on_both_worlds(tmp_path, router):
    raw = mixed_diamond()
    got = run_mixed(raw, tmp_path, router, fleet="mx")
    rep, j = got["report"], got["judge"]
    assert rep["success"] and rep["crashed"] == [], (tmp_path / "fleet.log").read_text()[-2000:]
    assert rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    mixed = rep["mixed"]
    assert mixed["real_robots"] == [0] and mixed["truth_from_estimate"] == [0] and mixed["pose_stale"] == []
    assert mixed["virtual_scans_sent"]["0"] > 50 and mixed["virtual_returns"]["0"]["merged_returns"] > 0
    assert rep["network"]["held_steps"].get("0", 0) > 0  # the real robot held (no-world) until the world ran
    sc = parse_scenario(raw, "mixed.yaml")
    assert j["clearance_m"]["0"] > 0.0, j  # the real robot never touched a simulated one, on the site's truth
    assert j["goal_error_m"]["0"] <= sc.success.goal_tolerance, j
    assert j["estimate_error_rms_m"]["0"] < 0.15 and j["formation_error_rms_m"] < 0.5, j
    # the recording: the virtual returns on their own channel, the real robot drawn as real; in the real viewer
    from mcap.reader import make_reader

    with open(tmp_path / "run" / "run.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    assert counts["/robot_0/virtual_scan"] > 50 and "/robot_1/virtual_scan" not in counts
    from lichtblick import Viewer

    with Viewer(tmp_path / "run") as v:
        v.open_recording("run.mcap", at_ns=summary.statistics.message_end_time)
        v.page.wait_for_timeout(2000)
        problems, listed = v.problems(), set(v.topics())
    assert not problems, "the viewer reports:\n" + "\n".join(problems)
    assert {"/robot_0/virtual_scan", TOPICS["robots"], "/robot_1/scan"} <= listed, sorted(listed)


def _parked_run(tmp_path: Path, router: str, virtual: bool, kill_at: float | None, run_s: float,
                mocap: tuple[float, float] | None = None):
    """The parked scenario: the fleet's world and the parked robot's agent, the site and the real robot's agent (its
    step log); the world SIGKILLed ``kill_at`` s after the real robot's first step; ``mocap`` (rate Hz, latency ms):
    the real robot's pose from the site's motion capture. Returns (records, kill wall time, the fleet's truth)."""
    raw = parked(virtual)
    if mocap is not None:
        raw["robots"][0]["pose_source"] = {"key": MOCAP_KEY}
    path = write_scenario(tmp_path / "parked.yaml", raw)
    steps = tmp_path / "steps-0.jsonl"
    with Site(raw, tmp_path / "site", router, mocap=() if mocap is None else (f"0:{MOCAP_KEY}:{mocap[0]}:{mocap[1]}",)):
        world = _popen(["stack-world", "--scenario", str(path), "--connect", router, "--fleet", "pk", "--realtime",
                        "--out", str(tmp_path / "run"), "--no-stop-early"], tmp_path / "world.log")
        agents = [_popen(["stack-agent", "--id", str(i), "--scenario", str(path), "--connect", router, "--fleet", "pk",
                          *(["--step-log", str(steps)] if i == 0 else [])], tmp_path / f"agent{i}.log") for i in (0, 1)]
        killed = None
        try:
            deadline = time.monotonic() + 60
            while not (steps.exists() and steps.stat().st_size) and time.monotonic() < deadline:
                time.sleep(0.1)  # (the log is buffered: its first 64 KiB come a few steps in)
            t0 = time.time()
            if kill_at is not None:
                time.sleep(max(0.0, kill_at - (time.time() - t0)))
                world.send_signal(signal.SIGKILL)
                killed = time.time()
            time.sleep(max(0.0, run_s - (time.time() - t0)))
        finally:
            for p in agents:
                _stop(p)
            _stop(world)
    truth = None
    if (tmp_path / "run" / "truth.npz").exists():
        with np.load(tmp_path / "run" / "truth.npz") as z:
            truth = {k: z[k] for k in z.files}
    return _records(steps), killed, truth


def test_a_real_robot_avoids_a_virtual_robot_it_sees_only_merged_and_slows_when_the_world_is_lost(tmp_path, router):
    recs, killed, _ = _parked_run(tmp_path, router, virtual=True, kill_at=8.0, run_s=12.0)
    sc = parse_scenario(parked(True), "parked.yaml")
    lid, r0, r1 = sc.robots[0].lidar, sc.robots[0].radius, sc.robots[1].radius
    before = [r for r in recs if r["now"] < killed]
    # it saw the parked robot (nothing stands in the site: any return is virtual) and kept its distance
    d = [np.hypot(r["out"]["pose"][0] - 2.2, r["out"]["pose"][1]) for r in before]
    assert min(min(r["scan"]["ranges"]) for r in before) < lid.range - 1.0
    assert min(d) > r0 + r1, f"closest {min(d):.2f} m"
    bound = lid.virtual_timeout + 2 * sc.dt  # the rule: gone within virtual_timeout (and a step either side)
    after = [r for r in recs if r["now"] > killed + bound]
    assert len(after) > 20, "the real robot's agent stopped with the world"
    assert all(min(r["scan"]["ranges"]) == lid.range for r in after), "a stale virtual return was kept"
    assert all(r["cmd"][0] <= lid.virtual_lost_speed + 1e-9 for r in after)
    assert max(r["cmd"][0] for r in after) > 0.0  # it goes on, slower: on its real scan alone


def test_without_the_merge_the_real_robot_drives_into_the_virtual_one(tmp_path, router):
    # its pose from a motion-capture system this time (30 Hz, 50 ms late): the world places the body where it says
    _, _, truth = _parked_run(tmp_path, router, virtual=False, kill_at=None, run_s=7.0, mocap=(30, 50))
    sc = parse_scenario(parked(False), "parked.yaml")
    d = np.hypot(truth["x"][:, 0] - truth["x"][:, 1], truth["y"][:, 0] - truth["y"][:, 1])
    assert d.min() < sc.robots[0].radius + sc.robots[1].radius  # the control case: the merge is what avoids it
    world = json.loads((tmp_path / "run" / "world.json").read_text())
    assert world["pose_sources"] == {"0": MOCAP_KEY} and world["poses_received"]["0"] > 100, world
    assert truth["x"][-1, 0] > 2.2  # it drove on through


def test_the_world_sees_a_real_robot_and_casts_virtual_scans_against_virtual_bodies_only():
    from stack.sim_bridge.world import World

    raw = parked(True)
    raw["world"] = {"obstacles": [{"type": "cylinder", "x": 0.0, "y": 2.0, "radius": 0.3},  # in the site
                                  {"type": "cylinder", "x": 0.0, "y": -2.0, "radius": 0.3, "virtual": True}]}
    raw["robots"][1]["pose"] = [0.0, 0.0, 0.0]  # the simulated robot, beside where the real one will be
    raw["robots"][0]["pose"] = [2.0, 0.0, 180.0]
    raw["robots"][0]["lidar"]["fov_deg"] = 360
    raw["robots"][0]["lidar"]["beams"] = 361
    w = World(parse_scenario(raw, "t.yaml"))
    try:
        w.place(0, 3.0, 0.0, 0.0, 0.0, 0.0)  # where its pose source says: not where it started
        sim = w.lidar([1])[1]
        ahead = sim[len(sim) // 2]  # the simulated robot's beam straight ahead (+x)
        assert ahead == pytest.approx(3.0 - 0.3, abs=0.02)  # it sees the real robot's body
        v = w.virtual_scan(0)
        ang = np.linspace(-np.pi, np.pi, 361)
        at = {name: v[int(np.argmin(np.abs(((ang - a + np.pi) % (2 * np.pi)) - np.pi)))]
              for name, a in (("sim robot", np.pi), ("virtual cylinder", np.arctan2(-2.0, -3.0)),
                              ("site cylinder", np.arctan2(2.0, -3.0)))}
        assert at["sim robot"] == pytest.approx(3.0 - 0.3, abs=0.02)
        assert at["virtual cylinder"] < 4.0 - 0.0 and at["site cylinder"] == 4.0  # the site's own: the real lidar's
        w.set_radius(0, 0.8)  # a stale pose: grown
        assert w.lidar([1])[1][len(sim) // 2] == pytest.approx(3.0 - 0.8, abs=0.02)
    finally:
        w.close()


def test_a_real_robot_whose_pose_goes_stale_is_grown_marked_and_casts_nothing(router):
    from stack.comm import Keys, encode
    from stack.comm.messages import State
    from stack.comm.session import SessionConfig, open_session
    from stack.fleet.viz_messages import robots_scene
    from stack.sim_bridge.real_robots import STALE_GROWTH_MAX_M, RealRobots
    from stack.sim_bridge.world import World

    sc = parse_scenario(parked(True), "parked.yaml")
    r0 = sc.robots[0]
    w, now, keys = World(sc), [100.0], Keys("stale")
    heard: list = []
    try:
        with open_session(SessionConfig(mode="client", connect=[router])) as s:
            real = RealRobots(w, sc, s, keys, clock=lambda: now[0])
            sub = s.declare_subscriber(keys.robot(0, "virtual_scan"), heard.append)
            pubs = {0: s.declare_publisher(keys.robot(0, "virtual_scan"))}
            state = s.declare_publisher(keys.robot(0, "state"))
            state.put(b"\x93not a state")  # counted per key, never taken
            state.put(encode(State(id=0, role="peer", seq=1, stamp=0.0, x=1.0, y=0.5, yaw=0.2, v=0.3, w=0.0)))
            assert wait_for(lambda: not real.waiting_for(), 5.0)
            assert real.place(0.0) == [] and (w.x[0], w.y[0], w.radii[0]) == (1.0, 0.5, r0.radius)
            real.publish_virtual(pubs, 0, 0.0, [])
            assert wait_for(lambda: len(heard) == 1, 5.0)
            now[0] += r0.pose_source.stale_after_s + 0.5  # 0.5 s past: it may have driven v_max * 0.5
            assert real.place(1.0) == [0] and w.radii[0] == pytest.approx(r0.radius + r0.v_max * 0.5)
            real.publish_virtual(pubs, 1, 1.0, [0])  # from a pose nobody trusts: nothing
            now[0] += 100.0
            assert real.place(2.0) == [0] and w.radii[0] == pytest.approx(r0.radius + STALE_GROWTH_MAX_M)
            assert "0 stale" in str(robots_scene(sc, {}, 0, {0}))
            state.put(encode(State(id=0, role="peer", seq=2, stamp=0.0, x=1.5, y=0.5, yaw=0.2, v=0.3, w=0.0)))
            assert wait_for(lambda: real.poses[0] == 2, 5.0)
            assert real.place(3.0) == [] and (w.x[0], w.radii[0]) == (1.5, r0.radius)
            time.sleep(0.3)
            assert len(heard) == 1
            rep = real.report()
            sub.undeclare()
            real.close()
    finally:
        w.close()
    assert rep["pose_stale"] == [{"robot": 0, "start": 1.0, "end": 3.0}] and rep["virtual_scans_sent"] == {"0": 1}
    assert rep["pose_malformed"] == {keys.robot(0, "state"): 1}


def test_a_motion_capture_pose_source_moves_the_body_at_the_speed_its_stamps_give(router):
    from stack.comm import Keys
    from stack.comm.session import SessionConfig, open_session
    from stack.drivers.ros2cdr import encode_pose_stamped
    from stack.sim_bridge.real_robots import RealRobots
    from stack.sim_bridge.world import World

    raw = parked(True)
    raw["robots"][0]["pose_source"] = {"key": "vrpn_mocap/speed/pose"}
    sc = parse_scenario(raw, "parked.yaml")
    w = World(sc)
    try:
        with open_session(SessionConfig(mode="client", connect=[router])) as s:
            real = RealRobots(w, sc, s, Keys("speed"))
            pub = s.declare_publisher("vrpn_mocap/speed/pose")
            pub.put(b"\x00\x01\x00\x00garbage")  # counted, never taken
            # a burst, as a 100 Hz system's samples come (arrival times say nothing, the capture stamps do), at
            # 0.5 m/s with a millimetre of jitter, one stamp twice and one pose repeated: the last two poses alone
            # would read 0 m/s (the world's settle check took a driving leader as stopped), the baseline does not
            xs = [1.0 + 0.005 * k + 0.001 * (-1) ** k for k in range(16)]
            xs[-1] = xs[-2]
            stamps = [10.0 + 0.01 * k for k in range(16)]
            for stamp, x in zip(stamps[:8] + [stamps[7]] + stamps[8:], xs[:8] + [xs[7]] + xs[8:]):
                pub.put(encode_pose_stamped(stamp, x, 0.0, 0.0))
            pub.put(encode_pose_stamped(9.5, 5.0, 0.0, 0.0))  # older than every one taken: counted, not placed
            assert wait_for(lambda: real.poses[0] == 17 and real.out_of_order[0] == 1, 5.0)
            real.place(0.0)
            assert w.x[0] == pytest.approx(xs[-1]) and w.v[0] == pytest.approx(0.5, abs=0.06)
            rep = real.report()
            real.close()
    finally:
        w.close()
    assert rep["pose_sources"] == {"0": "vrpn_mocap/speed/pose"} and rep["pose_malformed"] == {"vrpn_mocap/speed/pose": 1}
    assert rep["pose_out_of_order"] == {"0": 1}


def test_the_stand_in_site_has_the_real_robots_and_the_obstacles_that_are_not_virtual():
    raw = mixed_diamond()
    site = parse_scenario(reality_scenario(raw), "site.yaml")
    assert site.ids == [0] and site.robots[0].embodiment == "simulated" and site.robots[0].driver == "jackal"
    assert [o.type for o in site.obstacles] == ["wall"]


BAD = [
    (lambda r: r["robots"][0].update(driver="sim"), "robots[0].driver: a real robot needs the driver of its base"),
    (lambda r: r["robots"][0].update(odom_noise={"v_std": 0.1}), "robots[0].odom_noise: a real robot has no simulated"),
    (lambda r: r["robots"][0].update(device={"ideal": True}), "robots[0].device: a real robot has no simulated"),
    (lambda r: r["robots"][0].update(driver="can"), "robots[0].lidar.source: the world does not scan for a real robot"),
    (lambda r: r["robots"][0].update(pose_source={"key": "mocap/*"}), "robots[0].pose_source.key: not a Zenoh key"),
    (lambda r: r["robots"][0].update(pose_source={"topic": "x"}), "robots[0].pose_source.topic: unknown field"),
    (lambda r: r["robots"][1].update(pose_source={"key": "a/b"}), "robots[1].pose_source: only a real robot"),
    (lambda r: r["robots"][1].update(embodiment="virtual"), "robots[1].embodiment: expected one of simulated, real"),
    (lambda r: r["robots"][0].update(lidar={"virtual": "yes"}), "robots[0].lidar.virtual: expected true or false"),
]


@pytest.mark.parametrize("change, message", BAD, ids=[m.split(":")[0] for _, m in BAD])
def test_bad_mixed_settings_are_one_line_errors(change, message):
    raw = copy.deepcopy(mixed_diamond())
    change(raw)
    with pytest.raises(ScenarioError) as e:
        parse_scenario(raw, "mixed.yaml")
    assert message in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_a_real_robot_in_lock_step_or_faulted_by_the_fleet_is_a_one_line_error(tmp_path):
    path = write_scenario(tmp_path / "mixed.yaml", mixed_diamond())
    for extra, message in (([], "a fleet with real robots runs in real time (--realtime)"),
                           (["--realtime", "--kill", "0@3"], "robot 0 is real; its agent runs where the robot is")):
        p = run_cli(["stack-fleet", "run", str(path), "--out", str(tmp_path / "run"), *extra], timeout=60)
        assert p.returncode == 2 and message in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    p = run_cli(["stack-world", "--scenario", str(path), "--mocap", "0:vrpn/*/pose"], timeout=60)
    assert p.returncode == 2 and "not a Zenoh key" in p.stderr and "Traceback" not in p.stderr, p.stderr


def test_a_pose_source_that_never_publishes_is_a_one_line_error(tmp_path, router):
    raw = mixed_diamond()
    raw["robots"][0]["pose_source"] = {"key": "vrpn_mocap/nobody/pose"}
    path = write_scenario(tmp_path / "mixed.yaml", raw)
    p = run_cli(["stack-world", "--scenario", str(path), "--connect", router, "--fleet", "nobody", "--realtime",
                 "--no-agents", "--wait-agents", "1.5"], timeout=60)
    err = [ln for ln in p.stderr.splitlines() if not ln.startswith("pybullet build time")]
    assert p.returncode == 1 and len(err) == 1, p.stderr
    assert "real robot 0: no pose from PoseStamped on 'vrpn_mocap/nobody/pose' within 2 s" in err[0], err
