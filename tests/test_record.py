"""Issue 20: recordings (run.mcap with Foxglove schemas), the live view, the replay, the comm graph's counters.

Fleet tests start a router of their own, attach the recorder to it (as its own process, or in this one),
and run ``stack-fleet run --connect`` on that router: the recorder only listens."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from conftest import ROOT, run_fleet, scenario_dict, wait_port, write_scenario
from stack.comm import Keys, encode
from stack.comm.messages import Clock, Diag, Truth, WorldStatus, decode
from stack.comm.radio import RadioConfig, RadioModel
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session
from stack.fleet import viz_messages as vm
from stack.fleet.record import Recorder, RecorderConfig, RecorderError, parse_viz_endpoint
from stack.fleet.replay import ReplayError, decoder_factories, render_replay
from stack.scenario import parse_scenario
from stack.sim_bridge.geometry import pairwise_distances

PY = sys.executable
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


# --- the comm graph's counters ---------------------------------------------------------------------
def test_radio_counts_each_sender_and_the_sums_are_the_totals():
    radio = RadioModel(RadioConfig(comm_range=5.0, loss=0.3, seed=1), receiver_id=0)
    for k in range(200):
        radio.offer(1, (1.0, 0.0), (0.0, 0.0), k * 0.1, ("a", k))  # in range: delivered or lost
        radio.offer(2, (9.0, 0.0), (0.0, 0.0), k * 0.1, ("b", k))  # out of range: always dropped by range
        radio.ready(k * 0.1)
    links = radio.links()
    c = radio.counters.as_dict()
    assert set(links) == {1, 2}
    assert links[2] == {"delivered": 0, "dropped_range": 200, "dropped_loss": 0}
    assert links[1]["dropped_range"] == 0 and 30 < links[1]["dropped_loss"] < 90
    assert links[1]["delivered"] + links[1]["dropped_loss"] == 200
    for key in ("delivered", "dropped_range", "dropped_loss"):
        assert sum(v[key] for v in links.values()) == c[key]


def test_diag_links_is_optional_on_the_wire():
    old = Diag(id=1, stamp=0.0, step=0, state="running")
    assert decode(encode(old), Diag).links is None  # a sender that does not count per link
    new = Diag(id=1, stamp=0.0, step=0, state="running", links={2: {"delivered": 3, "dropped_range": 1, "dropped_loss": 0}})
    assert decode(encode(new), Diag).links == {2: {"delivered": 3, "dropped_range": 1, "dropped_loss": 0}}


# --- endpoints -------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, why", [("tcp/10.1.2.3:8765", "not a loopback"), ("localhost:8765", "PROTO/HOST:PORT"),
                                       ("udp/127.0.0.1:8765", "WebSocket over tcp"), ("tcp/127.0.0.1:99999", "out of range")])
def test_a_bad_viz_endpoint_is_a_one_line_error(text, why):
    with pytest.raises(ValueError) as e:
        parse_viz_endpoint(text)
    assert why in str(e.value) and "\n" not in str(e.value) and str(e.value).startswith("--viz:")
    assert parse_viz_endpoint(None) == ("127.0.0.1", 8765)
    assert parse_viz_endpoint("tcp/10.1.2.3:9000", allow_remote=True) == ("10.1.2.3", 9000)


def test_record_tool_rejects_a_bad_viz_endpoint_with_exit_2(tmp_path, diamond):
    proc = subprocess.run([PY, "-m", "stack.fleet.record", "--connect", "tcp/127.0.0.1:1", "--fleet", "x", "--scenario",
                           str(diamond), "--viz", "tcp/192.168.7.7:8765", "--wait", "0"],
                          capture_output=True, text=True, timeout=60, cwd=ROOT, env=ENV)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "not a loopback" in proc.stderr, proc.stderr


def test_a_live_port_in_use_is_a_one_line_error(tmp_path, diamond):
    import socket

    sc = parse_scenario(scenario_dict())
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        cfg = RecorderConfig(viz=f"tcp/127.0.0.1:{busy.getsockname()[1]}")
        with open_session(SessionConfig(mode="peer", listen=[free_tcp_endpoint()])) as s:
            with pytest.raises(RecorderError) as e:
                Recorder(s, Keys("busy"), sc, cfg).start()
    assert "\n" not in str(e.value) and "in use" in str(e.value)


# --- reading recordings back ---------------------------------------------------------------------------
def read_mcap(path: Path):
    """(summary, {topic: [(log_time, decoded)]}, metadata, attachments) of a recording, every message decoded."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=decoder_factories())
        summary = reader.get_summary()
        out: dict[str, list] = {}
        for _, ch, message, msg in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(ch.topic, []).append((message.log_time, msg))
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = {a.name: a.data for a in reader.iter_attachments()}
    return summary, out, meta, attachments


def _yaw(q) -> float:
    return 2.0 * math.atan2(q.z, q.w)


def _start_router(tmp_path: Path) -> tuple[str, subprocess.Popen]:
    ep = free_tcp_endpoint()
    log = open(tmp_path / "router.log", "wb")
    router = subprocess.Popen([PY, "-m", "stack.comm.router", "--listen", ep], stdout=log, stderr=subprocess.STDOUT,
                              cwd=ROOT, env=ENV)
    wait_port(ep)
    return ep, router


def _stop(proc: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL if it is still there 10 s later."""
    for end in (proc.terminate, proc.kill):
        if proc.poll() is None:
            end()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(10)


SCHEMAS = {"/clock": "stack.Clock", "/tf": "foxglove.FrameTransforms", "/tf_estimate": "foxglove.FrameTransforms",
           "/scene/obstacles": "foxglove.SceneUpdate", "/scene/robots": "foxglove.SceneUpdate",
           "/formation/slots": "foxglove.SceneUpdate", "/comm/links": "foxglove.SceneUpdate", "/metrics": "stack.Metrics",
           "/events": "foxglove.Log"}
ROBOT_SCHEMAS = {"pose": "foxglove.PoseInFrame", "estimate": "foxglove.PoseInFrame", "scan": "foxglove.LaserScan",
                 "cmd_vel": "stack.CmdVel", "state": "stack.State", "diag": "stack.Diag", "step_io": "stack.StepRecord"}


def _check_against_the_run(out: Path, summary, msgs: dict, meta: dict, step_io: bool = True) -> None:
    """``step_io``: the recording has the agents' step records (the fleet's own does, from its agents' --step-log
    files; a recorder elsewhere only if the agents publish them, ``stack-agent --log-steps``)."""
    world = json.loads((out / "world.json").read_text())
    rep = json.loads((out / "report.json").read_text())
    z = np.load(out / "truth.npz")
    ids = [int(i) for i in z["ids"]]
    steps, dt = world["steps"], rep["dt"]
    schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    want = SCHEMAS | {vm.robot_topic(r, k): s for r in ids for k, s in ROBOT_SCHEMAS.items() if step_io or k != "step_io"}
    assert schemas == want
    assert all(msgs.get(t) for t in want), [t for t in want if not msgs.get(t)]
    # one truth per step: /tf, every robot's pose, the scene, slots and metrics; one scan and one state per robot and step
    for topic in ["/tf", "/formation/slots", "/metrics", "/clock"] + [vm.robot_topic(r, "pose") for r in ids]:
        assert len(msgs[topic]) == steps, topic
    # the scene (obstacles; bodies locked to the robots' frames) once per second
    assert len(msgs["/scene/robots"]) == len(msgs["/scene/obstacles"]) == math.ceil(steps * dt - 1e-9)
    assert {e.frame_id for e in msgs["/scene/robots"][-1][1].entities} == {f"robot_{r}" for r in ids} | {f"robot_{r}/estimate" for r in ids}
    for r in ids:
        assert len(msgs[vm.robot_topic(r, "scan")]) == steps and len(msgs[vm.robot_topic(r, "state")]) == steps
        if step_io:  # every step's inputs
            assert [m["step"] for _, m in msgs[vm.robot_topic(r, "step_io")]] == list(range(steps))
        assert len(msgs[vm.robot_topic(r, "cmd_vel")]) >= steps
    assert len(msgs["/tf_estimate"]) == steps * len(ids)
    # sim time in lock-step: step k at k dt
    times = [ns for ns, _ in msgs["/tf"]]
    assert times == [round(k * dt * 1e9) for k in range(steps)]
    assert summary.statistics.message_start_time == 0
    assert abs(summary.statistics.message_end_time / 1e9 - rep["sim_time_s"]) <= dt + 1e-9
    # the poses are the world's ground truth, as truth.npz has them
    X = np.array([[{t.child_frame_id: t.translation.x for t in m.transforms}[f"robot_{r}"] for r in ids] for _, m in msgs["/tf"]])
    Y = np.array([[{t.child_frame_id: t.translation.y for t in m.transforms}[f"robot_{r}"] for r in ids] for _, m in msgs["/tf"]])
    assert np.array_equal(X, z["x"][:steps]) and np.array_equal(Y, z["y"][:steps])
    for j, r in enumerate(ids):
        yaw = np.array([_yaw(m.pose.orientation) for _, m in msgs[vm.robot_topic(r, "pose")]])
        assert np.allclose(np.angle(np.exp(1j * (yaw - z["yaw"][:steps, j]))), 0.0, atol=1e-9)
    # scans in the robot's frame, as many beams as the scenario's lidar
    scan = msgs[vm.robot_topic(ids[0], "scan")][0][1]
    assert scan.frame_id == f"robot_{ids[0]}" and len(scan.ranges) == 180
    hits = [r for rid in ids for _, m in msgs[vm.robot_topic(rid, "scan")] for r in m.ranges]  # followers see the others
    assert all(r == math.inf or 0 <= r < vm.NO_RETURN * 5.0 for r in hits) and math.inf in hits and min(hits) < 5.0
    assert {m["policy"] for _, m in msgs[vm.robot_topic(ids[0], "state")]} == {"pid"}
    assert all(m["cov_trace"] >= 0 for _, m in msgs[vm.robot_topic(ids[0], "state")])
    events = [m.message for _, m in msgs["/events"]]
    assert any(e.startswith("world: done") for e in events) and "0 dropped" in events[-1]
    metrics = [m for _, m in msgs["/metrics"]]
    dmin, _ = pairwise_distances(z["x"][:steps], z["y"][:steps])  # as the report computes it
    assert np.allclose([m["min_robot_distance"] for m in metrics], dmin, atol=1e-12)
    assert min(m["min_robot_distance"] for m in metrics) >= rep["min_robot_distance_m"] - 1e-4
    assert meta["stack.run"]["dropped"] == "0" and meta["stack.run"]["time"] == "sim"


@pytest.mark.fleet
def test_a_real_fleet_recorded_matches_its_report_and_truth_and_replays(tmp_path):
    sc = scenario_dict(duration=6.0)
    path = write_scenario(tmp_path / "d.yaml", sc)
    out = tmp_path / "out"
    ep, router = _start_router(tmp_path)
    rec = subprocess.Popen([PY, "-m", "stack.fleet.record", "--connect", ep, "--fleet", "rec1", "--scenario", str(path),
                            "--out", str(tmp_path / "rec")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           cwd=ROOT, env=ENV)
    try:
        assert "recording fleet" in rec.stdout.readline()
        proc, rep = run_fleet(path, out, "--connect", ep, "--fleet", "rec1", "--no-plots")
        assert rep is not None, proc.stderr
        assert rec.wait(30) == 0, rec.stderr.read()
    finally:
        _stop(rec)
        _stop(router)
    # the fleet's own recording (every run writes one) and the one of the tool that listened from outside
    _check_against_the_run(out, *read_mcap(out / "run.mcap")[:3])
    assert not (out / "replay.gif").exists()  # --no-plots: no replay either
    summary, msgs, meta, attachments = read_mcap(tmp_path / "rec" / "run.mcap")
    _check_against_the_run(out, summary, msgs, meta, step_io=False)
    assert parse_scenario(__import__("yaml").safe_load(attachments["scenario.yaml"])).ids == [0, 1, 2, 3]

    gif = render_replay(out, "replay.gif", max_frames=20, width=320)
    from PIL import Image

    with Image.open(gif) as im:
        assert im.n_frames == 20 and im.size == (320, 240)
    gif = render_replay(out / "run.mcap", "all.gif", max_frames=1000, width=200)
    with Image.open(gif) as im:
        assert im.n_frames == len(msgs["/tf"]) and im.size == (200, 150)


def test_replay_without_a_recording_is_a_one_line_error(tmp_path):
    with pytest.raises(ReplayError, match="no recording"):
        render_replay(tmp_path)
    (tmp_path / "run.mcap").write_bytes(b"not an mcap file")
    proc = subprocess.run([PY, "-m", "stack.fleet.replay", str(tmp_path)], capture_output=True, text=True, timeout=60,
                          cwd=ROOT, env=ENV)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "not a readable recording" in proc.stderr, proc.stderr


# --- the live view ------------------------------------------------------------------------------------------
def _ws_client(port: int, seen: dict, advertised: dict, stop: threading.Event) -> None:
    """A Foxglove WebSocket protocol client: subscribe to every channel advertised, count messages per topic."""
    import websockets

    async def run():
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
            subs: dict[int, str] = {}
            while not stop.is_set():
                try:
                    m = await asyncio.wait_for(ws.recv(), 0.2)
                except asyncio.TimeoutError:
                    continue
                if isinstance(m, str):
                    doc = json.loads(m)
                    if doc["op"] == "advertise":
                        new = [{"id": len(subs) + i + 1, "channelId": c["id"]} for i, c in enumerate(doc["channels"])]
                        for s, c in zip(new, doc["channels"]):
                            subs[s["id"]] = c["topic"]
                            advertised[c["topic"]] = c["schemaName"]
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                elif m[0] == 1:  # message data: opcode, subscription id, log time, payload
                    _, sid, _ = struct.unpack_from("<BIQ", m)
                    seen[subs[sid]] = seen.get(subs[sid], 0) + 1

    asyncio.run(run())


@pytest.mark.fleet
def test_a_live_client_receives_every_channel_of_a_realtime_run_stamped_in_wall_time(tmp_path):
    """--realtime: the live server serves every channel of the recording while the fleet runs; both on wall time."""
    sc = scenario_dict(duration=5.0)
    path = write_scenario(tmp_path / "d.yaml", sc)
    ep, router = _start_router(tmp_path)
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    seen: dict[str, int] = {}
    advertised: dict[str, str] = {}
    stop = threading.Event()
    cfg = RecorderConfig(out=tmp_path / "run.mcap", viz=f"tcp/127.0.0.1:{port}")
    try:
        with open_session(SessionConfig(connect=[ep])) as s:
            with Recorder(s, Keys("live1"), parse_scenario(sc), cfg) as rec:
                assert rec.port == port
                client = threading.Thread(target=_ws_client, args=(port, seen, advertised, stop), daemon=True)
                client.start()
                t0 = time.time_ns()
                proc, rep = run_fleet(path, tmp_path / "out", "--connect", ep, "--fleet", "live1", "--realtime", "--no-plots")
                t1 = time.time_ns()
                assert rep is not None, proc.stderr
                stop.set()
                client.join(10)
    finally:
        stop.set()
        _stop(router)
    want = SCHEMAS | {vm.robot_topic(r, k): s for r in range(4) for k, s in ROBOT_SCHEMAS.items()}
    assert advertised == want
    # every channel live but the step records, which the recorder writes from the agents' files when the run ends
    live = {t for t in want if not t.endswith("/step_io")}
    assert set(seen) == live, sorted(live - set(seen))
    assert seen["/tf"] >= 40 and seen["/robot_0/scan"] >= 40
    summary, msgs, meta, _ = read_mcap(tmp_path / "run.mcap")
    assert meta["stack.run"]["time"] == "wall"
    tf = [ns for ns, _ in msgs["/tf"]]
    assert t0 < tf[0] < tf[-1] < t1 and len(tf) == seen["/tf"]
    period = np.median(np.diff(tf)) / 1e9
    assert 0.05 < period < 0.2, period  # the world's wall-clock step, dt = 0.1 s


# --- the recorder alone, on real Zenoh ---------------------------------------------------------------------
def test_the_comm_graph_is_drawn_from_the_agents_link_counters(tmp_path):
    """Diag.links (cumulative, per sender) becomes a line per link over the last window, coloured by the worst."""
    sc = parse_scenario(scenario_dict())
    ep = free_tcp_endpoint()
    keys = Keys("links1")
    with open_session(SessionConfig(mode="peer", listen=[ep])) as s:
        rec = Recorder(s, keys, sc, RecorderConfig(out=tmp_path / "run.mcap", links_window_steps=10)).start()
        time.sleep(0.3)
        pub = {name: s.declare_publisher(key) for name, key in
               (("clock", keys.world("clock")), ("truth", keys.world("truth")), ("diag", keys.robot(1, "diag")))}
        truth = Truth(step=0, t=0.0, ids=[0, 1, 2, 3], x=[0.0, -2.0, -4.0, -2.0], y=[0.0, 2.0, 0.0, -2.0], yaw=[0.0] * 4)
        for k, links in ((0, {0: (5, 0, 0), 2: (5, 0, 0)}), (10, {0: (9, 0, 1), 2: (5, 5, 0)}), (20, {})):
            pub["clock"].put(encode(Clock(step=k, t=k * 0.1, dt=0.1)))
            pub["truth"].put(encode(msgspec.structs.replace(truth, step=k, t=k * 0.1)))
            d = {s_: dict(zip(("delivered", "dropped_range", "dropped_loss"), c)) for s_, c in links.items()}
            pub["diag"].put(encode(Diag(id=1, stamp=k * 0.1, step=k, state="running", links=d or None)))
            time.sleep(0.3)
        pub["diag"].put(b"\x93garbage")  # a payload that does not decode: counted, not written
        time.sleep(0.3)
        rec.stop()
    _, msgs, meta, _ = read_mcap(tmp_path / "run.mcap")
    scenes = [m for _, m in msgs["/comm/links"]]
    assert len(scenes) == 3
    last = {e.id: {kv.key: kv.value for kv in e.metadata} for e in scenes[-1].entities}
    assert last == {"link-0-1": {"delivered": "4", "dropped_range": "0", "dropped_loss": "1", "worst": "dropped_loss"},
                    "link-2-1": {"delivered": "0", "dropped_range": "5", "dropped_loss": "0", "worst": "dropped_range"}}
    line = {e.id: e.lines[0] for e in scenes[-1].entities}["link-0-1"]
    assert (line.points[0].x, line.points[0].y, line.points[1].x, line.points[1].y) == (0.0, 0.0, -2.0, 2.0)
    assert meta["stack.run"]["malformed"] == "1"


def test_a_full_queue_drops_and_counts_and_says_so(tmp_path):
    sc = parse_scenario(scenario_dict())
    with open_session(SessionConfig(mode="peer", listen=[free_tcp_endpoint()])) as s:
        rec = Recorder(s, Keys("full1"), sc, RecorderConfig(out=tmp_path / "run.mcap", queue_size=2))
        clock = ("clock", "stack/full1/world/clock", encode(Clock(step=0, t=0.0, dt=0.1)), 0)
        status = ("status", "stack/full1/world/status", encode(WorldStatus(state="running")), 0)
        for item in (clock, status, status, status):  # before the writer runs: two fit, two are dropped
            rec._put(item)
        assert rec.dropped == 2
        rec.start()
        rec.stop()
    _, msgs, meta, _ = read_mcap(tmp_path / "run.mcap")
    assert meta["stack.run"]["dropped"] == "2"
    assert "2 dropped" in msgs["/events"][-1][1].message
    assert [m["step"] for _, m in msgs["/clock"]] == [0]


def test_the_shipped_layout_shows_only_channels_a_recording_has():
    """docs/foxglove-layout.json: every topic its panels name is one the recorder writes (robots 0..7)."""
    layout = json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())
    known = set(vm.TOPICS.values()) | {vm.robot_topic(r, k) for r in range(8) for k in vm.ROBOT_TOPICS}
    cfg = layout["configById"]
    named = set(cfg["3D!fleet"]["topics"]) | {cfg["RosOut!events"]["topicToRender"]}
    paths = [p["value"] for panel in cfg.values() for p in panel.get("paths", [])]
    named |= {p.split(".")[0] for p in paths}
    assert named <= known, named - known
    assert {"/metrics.formation_error_rms", "/metrics.min_robot_distance", "/metrics.min_obstacle_distance"} <= set(paths)
    assert _json_fields("metrics") >= {p.split(".", 1)[1] for p in paths if p.startswith("/metrics.")}
    assert cfg["3D!fleet"]["followTf"] == vm.WORLD and "/comm/links" in named and "/robot_0/scan" in named

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(cfg)


def _json_fields(name: str) -> set[str]:
    return set(json.loads(vm.JSON_SCHEMAS[name].data)["properties"])


@pytest.mark.fleet
def test_no_record_writes_no_recording_and_a_run_with_plots_writes_its_replay(tmp_path):
    path = write_scenario(tmp_path / "d.yaml", scenario_dict(duration=3.0))
    proc, rep = run_fleet(path, tmp_path / "a", "--no-record")
    assert rep is not None, proc.stderr
    assert not (tmp_path / "a" / "run.mcap").exists() and not (tmp_path / "a" / "replay.gif").exists()
    assert (tmp_path / "a" / "trajectories.png").exists()
    proc, rep = run_fleet(path, tmp_path / "b")
    assert rep is not None, proc.stderr
    from PIL import Image

    with Image.open(tmp_path / "b" / "replay.gif") as im:  # two frames per second of the run, at least 10
        assert im.n_frames == 10 and im.size == (640, 480)
    assert "recording: " in proc.stdout and "replay: " in proc.stdout
