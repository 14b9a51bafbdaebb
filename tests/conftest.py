"""Shared helpers: small scenarios and running the real command-line tools as processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import stack  # noqa: F401  first: it pins numpy's BLAS kernels before numpy loads (stack/numerics.py)
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"


def scenario_dict(**over) -> dict:
    """A short four-robot diamond; followers start off their slots so they must move to them."""
    d = {
        "name": "test-diamond",
        "seed": 3,
        "dt": 0.1,
        "duration": 25.0,
        "world": {"obstacles": [{"type": "cylinder", "x": 6.0, "y": 5.0, "radius": 0.5},
                                {"type": "box", "x": 6.0, "y": -5.0, "size_x": 1.0, "size_y": 1.0, "yaw_deg": 10},
                                {"type": "wall", "from": [-6, 8], "to": [14, 8], "thickness": 0.2}]},
        "robot": {"radius": 0.5, "v_max": 1.0, "w_max": 1.0, "lidar": {"beams": 180, "fov_deg": 180, "range": 5.0, "noise_std": 0.0},
                  "comm_range": 10.0},
        "comm": {"loss": 0.0, "latency_ms": 0},
        "formation": {"leader": 0, "goal": [8.0, 0.0],
                      "slots": {1: {"L": 3.0, "psi_deg": 135}, 2: {"L": 4.0, "psi_deg": 180}, 3: {"L": 3.0, "psi_deg": -135}}},
        "robots": [
            {"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0]},
            {"id": 1, "role": "follower", "pose": [-1.0, 3.5, -30.0]},
            {"id": 2, "role": "follower", "pose": [-5.5, 1.0, 0.0]},
            {"id": 3, "role": "follower", "pose": [-1.0, -3.5, 30.0]},
        ],
        "success": {"goal_tolerance": 0.5, "max_time": 25.0, "no_collisions": True},
    }
    for k, v in over.items():
        d[k] = v
    return d


WALL_CLOCK = ("wall_time_s", "steps_per_s", "control_loop_ms", "control_compute_ms", "state_latency_ms", "planning")
"""Report entries measured on the wall clock: the only ones a lock-step run may change."""
WALL_CLOCK_ROBOT = ("device_odom_strays",)
"""Per robot, the same: how many samples a device sent on the wall clock before lock-step began were still on its
wire after the agent's sync step (dropped, counted; fresh-clone CI runs saw 0, 1 and 2 with the tracks the same to
the bit)."""


def lockstep_report(rep: dict) -> dict:
    """A report without what the wall clock measures: two lock-step runs of one seed give the same."""
    out = {k: v for k, v in rep.items() if k not in WALL_CLOCK}
    out["robots"] = {rid: {k: v for k, v in r.items() if k not in WALL_CLOCK_ROBOT} for rid, r in rep["robots"].items()}
    return out


def wait_for(pred, timeout: float = 2.0, step: float = 0.005):
    """Poll until pred() is truthy; returns its value (or the last falsy one)."""
    end = time.monotonic() + timeout
    while True:
        value = pred()
        if value or time.monotonic() > end:
            return value
        time.sleep(step)


def wait_port(endpoint: str, timeout: float = 20.0) -> None:
    """Until something listens on ``tcp/HOST:PORT`` (a router process that is still starting)."""
    import socket

    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    end = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=0.2):
                return
        except OSError:
            if time.monotonic() > end:
                raise TimeoutError(f"nothing listens on {endpoint} after {timeout:g} s") from None
            time.sleep(0.05)


def write_scenario(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run_cli(args: list[str], timeout: float = 180, **kw) -> subprocess.CompletedProcess:
    """Run a console tool as a real process (``python -m``, so the test does not depend on PATH)."""
    mod = {"stack-fleet": "stack.fleet", "stack-agent": "stack.agents", "stack-world": "stack.sim_bridge",
           "stack-router": "stack.comm.router", "stack-replay": "stack.replay.cli"}[args[0]]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for name in kw.pop("unset", ()):
        env.pop(name, None)
    return subprocess.run([sys.executable, "-m", mod, *args[1:]], capture_output=True, text=True, timeout=timeout,
                          cwd=kw.pop("cwd", ROOT), env=env, **kw)


def run_fleet(scenario: Path, out: Path, *extra: str, timeout: float = 180) -> tuple[subprocess.CompletedProcess, dict | None]:
    proc = run_cli(["stack-fleet", "run", str(scenario), "--out", str(out), "--no-progress", *extra], timeout=timeout)
    rep = out / "report.json"
    return proc, (json.loads(rep.read_text()) if rep.exists() else None)


@pytest.fixture(autouse=True)
def _signals_as_they_were():
    """Each test leaves SIGINT and SIGTERM as it found them. Code run in process (an agent's stop path sets both to
    SIG_IGN on its way out) would otherwise leave this interpreter ignoring them, and every process a later test
    starts inherits an ignored SIGINT: a Ctrl-C test's bench then ran on to the end."""
    import signal

    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    yield
    for sig, handler in saved.items():
        if handler is not None and signal.getsignal(sig) is not handler:
            signal.signal(sig, handler)


@pytest.fixture
def diamond(tmp_path: Path) -> Path:
    return write_scenario(tmp_path / "diamond.yaml", scenario_dict())
