"""Runs side by side (stack.fleet.jobs): --jobs N and --engine dask give the serial rows; ports never shared;
Ctrl-C stops every child fleet in order; bad engine flags are one-line errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROOT, run_cli, scenario_dict, write_scenario

TIMING = ("wall_time_s", "control_loop_ms", "control_compute_ms", "state_latency_ms", "steps_per_s")  # wall-clock measurements


ROBOTS = 2


def _folder(tmp_path: Path, duration: float, goal: tuple[float, float] | None = None) -> Path:
    """A bench folder with one scenario: the test diamond's leader and one follower (few processes a fleet)."""
    folder = tmp_path / "scenarios"
    folder.mkdir()
    d = scenario_dict(duration=duration)
    if goal is not None:
        d["formation"]["goal"] = list(goal)
    d["robots"] = d["robots"][:ROBOTS]
    d["formation"]["slots"] = {1: d["formation"]["slots"][1]}
    d["bench"] = {"policies": ["pid"]}
    write_scenario(folder / "short.yaml", d)
    return folder


def _lane(run: Path) -> tuple[str, str]:
    """(fleet name, router endpoint) the run's agent 0 was started with."""
    text = (run / "logs" / "agent-0.log").read_text()
    fleet = text.split("'fleet': '", 1)[1].split("'", 1)[0]
    endpoint = text.split(" up on ", 1)[1].split()[0]
    return fleet, endpoint


def test_ports_are_never_handed_out_twice(tmp_path):
    """Two processes allocating at once (the registry under TMPDIR): no port twice. Without the registry,
    300 draws of port 0 would repeat one most of the time (birthday bound over the ephemeral range)."""
    code = "from stack.fleet.ports import allocate_endpoint\nfor _ in range(150): print(allocate_endpoint())"
    env = dict(os.environ, TMPDIR=str(tmp_path))
    procs = [subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)
             for _ in range(2)]
    ports = [line for p in procs for line in p.communicate(timeout=60)[0].split()]
    assert all(p.returncode == 0 for p in procs) and len(ports) == 300
    assert len(set(ports)) == 300
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in ports)
    assert len(json.loads((tmp_path / f"stack-fleet-ports-{os.getuid()}.json").read_text())) == 300


def test_scheduler_address_is_loopback_unless_allowed():
    from stack.fleet.jobs import EngineError
    from stack.fleet.jobs_dask import check_scheduler

    assert check_scheduler("tcp://127.0.0.1:8786", False) == "tcp://127.0.0.1:8786"
    assert check_scheduler("tcp://10.0.0.5:8786", True) == "tcp://10.0.0.5:8786"
    for bad, msg in (("tcp://10.0.0.5:8786", "not a loopback address"), ("127.0.0.1:8786", "expected tcp://HOST:PORT"),
                     ("tcp://127.0.0.1:99999", "not a loopback address")):
        with pytest.raises(EngineError, match=msg):
            check_scheduler(bad, False)


def test_engine_flags_are_one_line_errors(tmp_path, capsys, monkeypatch):
    from stack.fleet.cli import cli

    def run(*flags: str) -> tuple[int, str]:
        try:
            code = cli(["bench", "--scenarios", str(tmp_path), "--out", str(tmp_path / "o"), "--sweep", "loss=0", *flags])
        except SystemExit as e:  # argparse's own errors (exit 2, one line)
            code = e.code
        return code, capsys.readouterr().err

    for flags, msg in ((["--jobs", "0"], "--jobs 0: expected at least 1"),
                       (["--scheduler", "tcp://127.0.0.1:8786"], "--scheduler: only with --engine dask"),
                       (["--engine", "dask", "--scheduler", "tcp://192.0.2.1:8786"], "needs --allow-remote"),
                       (["--engine", "dask", "--scheduler", "tcp://127.0.0.1:8786", "--jobs", "2"], "the cluster's workers"),
                       (["--engine", "spark"], "invalid choice")):
        code, err = run(*flags)
        assert code == 2 and msg in err and len(err.strip().splitlines()) == 1, (flags, err)
    monkeypatch.setitem(sys.modules, "distributed", None)  # the dist extra not installed: the import fails
    code, err = run("--engine", "dask")
    assert code == 2 and "needs the dist extra" in err and len(err.strip().splitlines()) == 1, err
    proc = subprocess.run([sys.executable, "bench/heldout.py", "--jobs", "0"], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and "--jobs 0: expected at least 1" in proc.stderr, proc.stderr


@pytest.mark.fleet
def test_parallel_and_dask_sweeps_give_the_serial_rows(tmp_path):
    """A 2-run loss sweep with --jobs 1, --jobs 2 and --engine dask (a LocalCluster on 127.0.0.1): the same rows,
    the same reports (wall times aside); side by side, each run its own fleet name and router port."""
    folder = _folder(tmp_path, duration=1.5)
    rows, reports = {}, {}
    engines = (("serial", ["--jobs", "1"]), ("jobs2", ["--jobs", "2"]), ("dask", ["--engine", "dask", "--jobs", "2"]))
    for name, flags in engines:
        out = tmp_path / name
        proc = run_cli(["stack-fleet", "bench", "--scenarios", str(folder), "--out", str(out), "--sweep", "loss=0,0.5",
                        "--seeds", "1", *flags], timeout=240)
        assert proc.returncode == 0, (name, proc.stderr[-2000:])
        rows[name] = json.loads((out / "loss_sweep.json").read_text())["rows"]
        runs = sorted(p.parent for p in out.glob("*/report.json"))
        assert len(runs) == 2, runs
        reports[name] = [{k: v for k, v in json.loads((r / "report.json").read_text()).items() if k not in TIMING}
                         for r in runs]
        lanes = [_lane(r) for r in runs]
        assert len({f for f, _ in lanes}) == 2 and len({e for _, e in lanes}) == 2, lanes
    assert rows["serial"][1]["delivered_share"] < 0.8  # the loss model was in the loop
    assert rows["jobs2"] == rows["serial"] and rows["dask"] == rows["serial"]
    assert reports["jobs2"] == reports["serial"] and reports["dask"] == reports["serial"]


@pytest.mark.fleet
@pytest.mark.parametrize("engine", [["--jobs", "2"], ["--engine", "dask", "--jobs", "2"]], ids=["local", "dask"])
def test_ctrl_c_stops_every_child_fleet_in_order(tmp_path, engine):
    """Ctrl-C (SIGINT to the terminal's process group) with two fleets running: exit 130, the run not yet started
    never starts, every agent got its SIGTERM (zero velocity on the way out), no process of the runs (nor a Dask
    worker) is left."""
    folder = _folder(tmp_path, duration=120.0, goal=(500.0, 0.0))  # no run ends by itself before the Ctrl-C
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "stack.fleet", "bench", "--scenarios", str(folder), "--out", str(out),
                          "--sweep", "loss=0", "--seeds", "3", *engine], cwd=ROOT, start_new_session=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_sigint_default)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # every agent of both fleets up
            logs = list(out.glob("*/logs/agent-*.log"))
            if len(logs) == 2 * ROBOTS and all(" up on " in f.read_text() for f in logs):
                break
            time.sleep(0.2)
        else:
            raise AssertionError("the two fleets never came up")
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130 and "interrupted" in err, err[-2000:]
    runs = sorted(d for d in out.iterdir() if d.is_dir())
    assert [d.name[-2:] for d in runs] == ["s0", "s1"], runs  # seed 2 was never started
    for r in runs:
        for rid in range(ROBOTS):
            log = (r / "logs" / f"agent-{rid}.log").read_text()
            assert "SIGTERM: stopping" in log, (r.name, rid, log[-500:])
    assert not _left(out, p.pid), _left(out, p.pid)


def _sigint_default() -> None:
    """The bench starts as a terminal starts it, SIGINT at its default, whatever this test process inherited (a
    shell's background job, or a test run in process before, can leave SIGINT ignored, and an ignored SIGINT is
    inherited across exec: the fresh-clone CI's bench then ran all its runs to the end)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _left(out: Path, pgid: int, wait_s: float = 10.0) -> list[str]:
    """Processes of the runs under ``out`` or in the bench's process group (Dask workers), zombies aside."""
    deadline = time.monotonic() + wait_s
    while True:
        ps = subprocess.run(["ps", "-eo", "pgid=,stat=,args="], capture_output=True, text=True).stdout.splitlines()
        left = [line for line in ps if (str(out) in line or line.split()[0] == str(pgid)) and line.split()[1][0] != "Z"]
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.5)
