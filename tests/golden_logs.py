"""Golden step logs: short recorded runs whose every robot must replay to the bit (tests/test_replay.py).

A change that alters any policy's decisions (or the estimator, the guard, the decision layer) makes a golden
log stop reproducing, and the test names the log, the robot and the first step that differs. When the change is
meant, record them again (a minute or two; then look at the diff of what changed and commit the files):

    make golden            # = .venv/bin/python tests/golden_logs.py

Each case is a ``stack-fleet run`` (recording on), cut down to the robots' ``/robot_<id>/step_io`` channels (and ``/robot_<id>/state``: the records name the states
they took)
(``tests/golden/<name>.mcap``, zstd chunks): lock-step runs of every policy (PID on the diamond; aina, fuzzy,
qlearn and the DRL network on the obstacle course), a lock-step fleet of hardware-like devices (one robot per
driver: mavlink, can, jackal, sim), and a real-time Jackal fleet on hardware-like devices (lidar at 15 Hz, the
robot's clock 3.7 s ahead, dropped samples) with 10 % radio loss.
"""

from __future__ import annotations

import copy
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
GOLDEN = HERE / "golden"
sys.path.insert(0, str(HERE))

from conftest import scenario_dict  # noqa: E402

DEVICE = {"jackal": {"lidar_rate_hz": 15.0, "clock_offset_s": 3.7, "jitter_s": 0.002, "drop_prob": 0.05}}


def _devices() -> dict:
    d = scenario_dict(duration=4.0)
    d["name"] = "golden-devices"
    d["robot"]["device"] = copy.deepcopy(DEVICE)
    for r, driver in zip(d["robots"], ("mavlink", "can", "jackal", "sim")):
        r["driver"] = driver
    return d


def _realtime() -> dict:
    d = scenario_dict(duration=4.0)
    d["name"] = "golden-realtime"
    d["robot"]["device"] = copy.deepcopy(DEVICE)
    return d


CASES: dict[str, tuple[object, list[str]]] = {
    # name: (scenario file or dict, stack-fleet run flags)
    "diamond-pid": ("scenarios/four-robot-diamond.yaml", ["--duration", "4"]),
    "obstacles-aina": ("scenarios/four-robot-obstacles.yaml", ["--duration", "5", "--policy", "aina"]),
    "obstacles-fuzzy": ("scenarios/four-robot-obstacles.yaml", ["--duration", "5", "--policy", "fuzzy"]),
    "obstacles-qlearn": ("scenarios/four-robot-obstacles.yaml", ["--duration", "5", "--policy", "qlearn"]),
    "obstacles-drl": ("scenarios/four-robot-obstacles.yaml", ["--duration", "5", "--policy", "drl"]),
    "devices-lockstep": (_devices(), ["--lockstep-timeout", "10"]),
    "realtime-jackal": (_realtime(), ["--realtime", "--driver", "jackal", "--loss", "0.1"]),
}


def extract(run_mcap: Path, out: Path) -> int:
    """``out``: only the step_io and state channels of ``run_mcap`` (their schemas, every message, in order); the
    number of step records kept."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    n = 0
    with run_mcap.open("rb") as f, out.open("wb") as g:
        reader = make_reader(f)
        w = Writer(g, compression=CompressionType.ZSTD)
        w.start(profile="", library="stack tests/golden_logs.py")
        ids: dict[int, int] = {}
        for schema, channel, msg in reader.iter_messages():
            if not channel.topic.endswith(("/step_io", "/state")) or not channel.topic.startswith("/robot_"):
                continue  # the step records, and the states they name (steplog.StateRefs)
            if channel.id not in ids:
                sid = w.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = w.register_channel(channel.topic, channel.message_encoding, sid)
            w.add_message(ids[channel.id], msg.log_time, msg.data, msg.publish_time)
            n += channel.topic.endswith("/step_io")
        w.finish()
    return n


def record(names: list[str] | None = None) -> None:
    GOLDEN.mkdir(exist_ok=True)
    for name, (scenario, flags) in CASES.items():
        if names and name not in names:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"{name}.yaml"
            if isinstance(scenario, dict):
                path.write_text(yaml.safe_dump(scenario, sort_keys=False))
            else:
                shutil.copy(ROOT / scenario, path)
            out = Path(tmp) / "out"
            p = subprocess.run([sys.executable, "-m", "stack.fleet", "run", str(path), "--out", str(out), "--no-plots",
                                "--no-progress", *flags], cwd=ROOT, capture_output=True, text=True)
            if not (out / "run.mcap").exists():
                sys.exit(f"golden {name}: the run left no run.mcap (exit {p.returncode}): {p.stderr[-800:]}")
            n = extract(out / "run.mcap", GOLDEN / f"{name}.mcap")
        print(f"{name}: {n} step records -> {GOLDEN / (name + '.mcap')} ({(GOLDEN / (name + '.mcap')).stat().st_size // 1024} KiB)")


if __name__ == "__main__":
    record(sys.argv[1:])
