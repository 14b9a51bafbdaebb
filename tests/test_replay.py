"""Issue 40: a robot's step log replays to the bit; a change's first divergence is found, shown and right.

The golden logs (tests/golden_logs.py: lock-step runs of every policy, a lock-step fleet of hardware-like devices,
a real-time Jackal fleet with 10 % loss) replay to the bit for every robot: a change that alters any decision
fails here, naming the log, the robot and the step. A changed gain's reported step is checked against a
lock-step run with that gain from the start. Torn, corrupt, gapped and future-version logs are one-line errors
or counted stops. (Live runs replayed to the bit: tests/test_hil_fleet.py, real time on hardware-like Jackals
with loss, and restarted agents; tests/test_agent_view.py, an agent's own ``--record``, lock-step and real time.)
"""

from __future__ import annotations

import math
import os
import platform
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest
import yaml

from conftest import ROOT, run_cli, run_fleet, write_scenario
from golden_logs import CASES, GOLDEN, extract
from stack.agents import steplog
from stack.agents.step import OdomSample, StepInputs, StepOutput
from stack.comm.messages import State
from stack.estimation.pose import Pose
from stack.replay.cli import main as replay_main
from stack.replay.cli import verify
from stack.replay.log import read_log
from stack.replay.run import Changes, differing, replay


def test_every_golden_case_has_its_log_and_every_log_its_case():
    assert sorted(p.stem for p in GOLDEN.glob("*.mcap")) == sorted(CASES)


@pytest.mark.parametrize("name", sorted(CASES))
def test_a_golden_log_replays_to_the_bit(name, capsys):
    """If this fails after a change that is meant to alter decisions: ``make golden`` (tests/golden_logs.py)."""
    path = GOLDEN / f"{name}.mcap"
    code = verify(path)
    out = capsys.readouterr().out
    assert code == 0, f"golden log {name} no longer reproduces (re-record with `make golden` if meant):\n{out}"
    assert "all 4 robots reproduced to the bit" in out


def _first_difference(a, b) -> int | None:
    """The first step whose recorded outputs differ between two logs of one robot (lock-step: same steps)."""
    for ra, rb in zip(a.segments[0].records, b.segments[0].records):
        assert ra.step == rb.step
        if differing(ra.out, rb.out):
            return ra.step
    return None


@pytest.mark.fleet
def test_a_changed_gain_diverges_at_the_step_a_run_with_that_gain_first_differs(tmp_path):
    src = yaml.safe_load((ROOT / "scenarios/four-robot-diamond.yaml").read_text())
    entry = next(r for r in src["robots"] if r["id"] == 1)
    entry["pid"] = dict(entry.get("pid") or {}) | {"k_v": 1.5}
    src["duration"] = 1.0  # the golden run's first second with the gain changed from the start
    proc, rep = run_fleet(write_scenario(tmp_path / "kv.yaml", src), tmp_path / "kv", "--no-plots")
    assert rep is not None and not rep["crashed"], proc.stdout + proc.stderr
    golden = read_log(GOLDEN / "diamond-pid.mcap", 1)
    truth = _first_difference(golden, read_log(tmp_path / "kv" / "run.mcap", 1))
    assert truth is not None and truth > 0  # it matters, and not from the first step (the follower starts at v_max)

    p = run_cli(["stack-replay", str(GOLDEN / "diamond-pid.mcap"), "--robot-id", "1", "--set", "robot.pid.k_v=1.5",
                 "--out", str(tmp_path / "replay")])
    assert p.returncode == 1, p.stdout + p.stderr
    first = p.stdout.splitlines()[0]
    assert first.startswith(f"first divergence: step {truth} "), (truth, first)
    assert "| step | t [s] | v recorded | v replayed |" in p.stdout
    png, mcap = tmp_path / "replay" / "replay-robot_1.png", tmp_path / "replay" / "replay-robot_1.mcap"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    from mcap.reader import make_reader

    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
    counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    steps = len(golden.segments[0].records)
    assert counts == {"/robot_1/recorded/cmd_vel": steps, "/robot_1/replayed/cmd_vel": steps,
                      "/robot_1/recorded/estimate": steps, "/robot_1/replayed/estimate": steps, "/replay/events": 1}
    # seen as a user sees it: the replay's MCAP opens in the real viewer (tests/lichtblick.py) with no problem
    from lichtblick import Viewer

    with Viewer(tmp_path / "replay") as v:
        v.open_recording(mcap.name, at_ns=summary.statistics.message_end_time)
        v.page.wait_for_timeout(2000)
        problems, listed = v.problems(), set(v.topics())
    assert not problems, "the viewer reports:\n" + "\n".join(problems)
    assert set(counts) <= listed, sorted(set(counts) - listed)


def test_changes_that_make_no_difference_and_bad_changes(capsys):
    path = str(GOLDEN / "diamond-pid.mcap")
    assert replay_main([path, "--robot-id", "0", "--set", "robot.pid.k_d=0.3"]) == 0  # a leader at cruise: no D term
    assert "the change makes no difference" in capsys.readouterr().out
    for argv, msg in [
        (["--robot-id", "0", "--set", "robot.pid.bogus=1"], "robots[0].pid.bogus: unknown field"),
        (["--robot-id", "0", "--set", "robot.pid.k_v"], "expected KEY=VALUE"),
        (["--robot-id", "0", "--set", "robot.pid.k_v=-3"], "robots[0].pid.k_v"),
        (["--robot-id", "9"], "no step log of robot 9 (robots [0, 1, 2, 3])"),
        ([], "step logs of robots [0, 1, 2, 3]: name one (--robot-id N)"),
        (["--robot-id", "0", "--top", "0"], "--top: must be >= 1"),
    ]:
        assert replay_main([path, *argv]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and msg in err, (argv, err)


def test_policy_swap_diverges_and_names_what_differs(tmp_path, capsys):
    code = replay_main([str(GOLDEN / "obstacles-aina.mcap"), "--robot-id", "2", "--policy", "fuzzy", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 1 and out.startswith("first divergence: step "), out
    assert (tmp_path / "replay-robot_2.png").exists() and (tmp_path / "replay-robot_2.mcap").exists()


# --- bad logs -------------------------------------------------------------------------------------------------
def _rewrite(src: Path, dst: Path, edit, chunk_size: int = 1024 * 1024, states=lambda d: d) -> None:
    """``dst``: ``src`` with every step record passed through ``edit(dict) -> dict | None`` (None: left out); the
    states as they were (``states``: the same for each state's document)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with src.open("rb") as f, dst.open("wb") as g:
        w = Writer(g, chunk_size=chunk_size)
        w.start()
        ids = {}
        for schema, ch, msg in make_reader(f).iter_messages():
            doc = (edit if ch.topic.endswith("/step_io") else states)(msgspec.json.decode(msg.data))
            if doc is None:
                continue
            if ch.id not in ids:
                ids[ch.id] = w.register_channel(ch.topic, ch.message_encoding,
                                                w.register_schema(schema.name, schema.encoding, schema.data))
            w.add_message(ids[ch.id], msg.log_time, msgspec.json.encode(doc), msg.publish_time)
        w.finish()


def test_a_log_from_a_newer_schema_is_one_line(tmp_path, capsys):
    _rewrite(GOLDEN / "diamond-pid.mcap", tmp_path / "v2.mcap", lambda d: d | {"version": 2, "new_field": [1]})
    assert replay_main([str(tmp_path / "v2.mcap"), "--robot-id", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "schema version 2, this stack reads version 1" in err and "newer" in err, err


def test_a_torn_or_corrupt_log_stops_at_its_last_whole_step(tmp_path, capsys):
    whole = read_log(GOLDEN / "diamond-pid.mcap", 3).steps
    _rewrite(GOLDEN / "diamond-pid.mcap", tmp_path / "small-chunks.mcap", lambda d: d, chunk_size=16 * 1024)
    data = (tmp_path / "small-chunks.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) * 2 // 3])
    assert replay_main([str(tmp_path / "cut.mcap"), "--robot-id", "3"]) == 0  # what is there reproduces
    cap = capsys.readouterr()
    n = int(cap.out.split(" steps replayed")[0].rsplit(" ", 1)[-1])
    assert 0 < n < whole, cap.out
    assert "stopped early: the file ends in a torn or corrupt record" in cap.err and f"{n} whole steps" in cap.err
    assert len(cap.err.strip().splitlines()) == 1
    bad = bytearray(data)
    mid = len(bad) // 2
    bad[mid:mid + 64] = bytes(64)  # zeros over the middle of a compressed chunk: its CRC (or zstd) says so
    (tmp_path / "corrupt.mcap").write_bytes(bytes(bad))
    assert replay_main([str(tmp_path / "corrupt.mcap"), "--robot-id", "3"]) in (0, 2)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and ("torn or corrupt" in err), err
    for name, content in (("empty.mcap", b""), ("text.mcap", b"not a recording\n" * 20)):
        (tmp_path / name).write_bytes(content)
        assert replay_main([str(tmp_path / name)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "not an MCAP file" in err, err


def test_a_gap_in_a_log_stops_the_replay_before_it(tmp_path, capsys):
    _rewrite(GOLDEN / "diamond-pid.mcap", tmp_path / "gap.mcap", lambda d: None if d["n"] == 20 else d)
    assert replay_main([str(tmp_path / "gap.mcap"), "--robot-id", "2"]) == 0
    cap = capsys.readouterr()
    assert "robot 2: 20 steps replayed" in cap.out, cap.out
    assert "a gap in robot 2's log after step 19 (records 20..20 lost on the way)" in cap.err, cap.err
    # a fleet's records name the states they took; one the recorder lost stops the replay the same way
    _rewrite(GOLDEN / "diamond-pid.mcap", tmp_path / "nostate.mcap", lambda d: d,
             states=lambda d: None if (d["id"], d["step"]) == (0, 9) else d)
    assert replay_main([str(tmp_path / "nostate.mcap"), "--robot-id", "2"]) == 0
    cap = capsys.readouterr()
    assert "robot 2: 10 steps replayed" in cap.out, cap.out
    assert "robot 2's step 10 took robot 0's state seq 10, which the recording does not have" in cap.err, cap.err
    assert verify(tmp_path / "nostate.mcap") == 1
    assert "reproduced only up to where their logs stop" in capsys.readouterr().out


def test_a_record_the_step_cannot_take_and_bad_setups_are_one_line(tmp_path, capsys):
    def bad_guard(d):
        if d.get("setup"):
            d["setup"]["step_config"]["guard"]["margin"] = -5.0
        return d

    def bad_scan(d):
        if d["n"] == 3 and d.get("scan"):
            d["scan"]["ranges"] = d["scan"]["ranges"][:7]  # a scan of another lidar than the recorded robot's
        return d

    for name, edit, msg in (("guard.mcap", bad_guard, "do not build a pipeline here"),
                            ("scan.mcap", bad_scan, "step 3: the step pipeline raised")):
        _rewrite(GOLDEN / "obstacles-aina.mcap", tmp_path / name, edit)
        assert replay_main([str(tmp_path / name), "--robot-id", "1"]) == 2, name
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and msg in err, (name, err)


def test_a_recording_without_step_records_says_why(tmp_path, capsys):
    _rewrite(GOLDEN / "diamond-pid.mcap", tmp_path / "mid.mcap", lambda d: None if d["n"] < 5 else d)
    assert replay_main([str(tmp_path / "mid.mcap"), "--robot-id", "0"]) == 2
    assert "the recording began after the agent had started" in capsys.readouterr().err


# --- the record itself ------------------------------------------------------------------------------------------
def _bits(x: float) -> bytes:
    return struct.pack("<d", x)


def test_a_record_keeps_every_float_to_the_bit_non_finite_ones_too():
    class _Pl:  # what StepLogger reads of a pipeline
        id, role, policy_name, seed = 4, "peer", "pid", 7
        guard = type("G", (), {"capped": 3, "slides": 1})()
        neighbours = {3: None, 1: None}
        planner = type("R", (), {"adopted_now": [2, 5]})()

    pl = _Pl()
    weird = [0.1 + 0.2, -0.0, 5e-324, 1.7976931348623157e308, math.pi, float("nan"), float("inf"), -float("inf")]
    samples = tuple(OdomSample(v=x, w=-x, t=1.0 + i, wz_imu=x, pose=(x, 2.0, -x), fix=(x, x, 0.3))
                    for i, x in enumerate(weird))
    inp = StepInputs(step=5, t=0.5, t_run=0.5, now=1.7e9 + 0.123456789, odometry=samples, fixes=((1 / 3, 2 / 3, 0.3),),
                     dead=frozenset({2, 1}), held="no-network", goal=(1.25, -3.5))
    out = StepOutput(v=1 / 7, w=-0.0, pose=Pose(1 / 3, 2.0, -1.0, 0.0, 0.0), situation="peer", cov_trace=1e-9,
                     d_goal=None, stale=None, target=(0.1, 0.2))
    logger = steplog.StepLogger.__new__(steplog.StepLogger)
    logger.pl, logger.setup, logger.n, logger._scan, logger._enc = pl, None, 0, None, msgspec.json.Encoder()
    logger.refs = False
    rec = steplog.decode(logger.record(inp, out, (0.1, 0.0)))
    back = steplog.inputs_of(rec, None)
    for a, b in zip(samples, back.odometry):
        for fa, fb in zip((a.v, a.w, a.t, a.wz_imu, *a.pose, *a.fix), (b.v, b.w, b.t, b.wz_imu, *b.pose, *b.fix)):
            assert _bits(fa) == _bits(fb) or (math.isnan(fa) and math.isnan(fb)), (fa, fb)
    assert back.fixes == inp.fixes and back.dead == inp.dead and back.held == "no-network" and back.goal == (1.25, -3.5)
    assert back.plans == (2, 5)  # the plans the step adopted: a replay adopts them at the same step
    assert _bits(back.now) == _bits(inp.now)
    assert _bits(rec.out.w) == _bits(-0.0) and rec.out.v == 1 / 7 and (rec.out.guard_caps, rec.out.guard_slides) == (3, 1)
    assert rec.out.heard == [1, 3]
    st = State(id=3, role="follower", seq=12, stamp=1.7e9 + 1 / 3, x=1.0, y=2.0, yaw=0.5, v=0.1, w=0.0, wall=1.7e9)
    logger.refs = True  # a fleet's record: the states by name (the recording has each once)
    named = steplog.decode(logger.record(StepInputs(step=6, t=0.6, t_run=0.6, now=0.6, states=(st,)), out, (0.0, 0.0)))
    assert named.states == [] and named.state_refs == steplog.StateRefs([3], [12], [st.stamp]) and named.n == 1
    assert not differing(rec.out, steplog.out_of(out, pl))
    assert differing(rec.out, steplog.out_of(StepOutput(**{**out.__dict__, "w": 0.0}), pl)) == ("w",)


def test_the_golden_logs_can_be_extracted_from_a_run(tmp_path):
    """What ``make golden`` does to a run's recording keeps every step record (and only those)."""
    n = extract(GOLDEN / "diamond-pid.mcap", tmp_path / "again.mcap")
    assert n == sum(read_log(GOLDEN / "diamond-pid.mcap", r).steps for r in range(4))
    shutil.copy(tmp_path / "again.mcap", tmp_path / "copy.mcap")
    for rid in range(4):
        assert replay(read_log(tmp_path / "copy.mcap", rid), Changes()).reproduced


def test_other_weights_change_the_networks_decisions(tmp_path, capsys):
    """``--set robot.drl.weights=FILE``: the same recorded steps through the training chain's weights."""
    chain = ROOT / "stack/policies/drl/weights/drl-chain.pt"
    code = replay_main([str(GOLDEN / "obstacles-drl.mcap"), "--robot-id", "1", "--set", f"robot.drl.weights={chain}",
                        "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 1 and out.startswith("first divergence: step "), out
    missing = replay_main([str(GOLDEN / "obstacles-drl.mcap"), "--robot-id", "0", "--set", "robot.drl.weights=nope.npz"])
    err = capsys.readouterr().err.strip()
    assert missing == 2 and len(err.splitlines()) == 1 and "nope.npz" in err, err


def test_bad_step_log_and_out_paths_are_one_line(tmp_path, capsys):
    p = run_cli(["stack-agent", "--id", "1", "--scenario", str(ROOT / "scenarios/four-robot-diamond.yaml"),
                 "--connect", "tcp/127.0.0.1:9", "--step-log", str(tmp_path / "no" / "such" / "dir" / "s.jsonl")], timeout=60)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "--step-log" in p.stderr, p.stderr
    (tmp_path / "file").write_text("x")
    code = replay_main([str(GOLDEN / "diamond-pid.mcap"), "--robot-id", "1", "--set", "robot.pid.k_v=1.5",
                        "--out", str(tmp_path / "file" / "sub")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "cannot write" in err, err


def _core_in_a_fresh_process(**env) -> str:
    e = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"} | env
    out = subprocess.run([sys.executable, "-c", "import stack, stack.numerics as n; print(n.blas_core())"],
                         capture_output=True, text=True, env=e, timeout=60, check=True).stdout
    return out.strip().splitlines()[-1]


def test_every_x86_machine_with_avx2_runs_the_same_blas_kernels_so_logs_replay_across_machines():
    """A log recorded on an AVX2 machine (OpenBLAS Haswell kernels) replays to the bit on an AVX-512 one only if
    both run one kernel set: stack pins it before numpy loads; a user's OPENBLAS_CORETYPE wins."""
    from stack.numerics import PINNED_CORE, _has_avx2_fma, blas_core

    if platform.machine() == "x86_64" and _has_avx2_fma():
        assert blas_core() == PINNED_CORE  # this test process (conftest imports stack first)
        assert _core_in_a_fresh_process() == PINNED_CORE
        assert _core_in_a_fresh_process(OPENBLAS_CORETYPE="Prescott") != PINNED_CORE
    else:  # nothing pinned: OpenBLAS picks its own
        assert "OPENBLAS_CORETYPE" not in os.environ
