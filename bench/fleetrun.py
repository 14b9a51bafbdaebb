"""What the fleet benchmarks share: a scenario with per-robot policy settings over it, and one
``stack-fleet run`` as a process, its report read back."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml


def scenario_with(scenario: Path, block: str, over: dict, out: Path, tag: str) -> Path:
    """``scenario`` itself when ``over`` is empty; else a copy in ``out`` with ``robot.<block>`` updated by ``over``
    (every robot: the scenario's ``robot:`` defaults)."""
    if not over:
        return scenario
    raw = yaml.safe_load(scenario.read_text())
    robot = dict(raw.get("robot") or {})
    robot[block] = dict(robot.get(block) or {}) | over
    raw["robot"] = robot
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{scenario.stem}-{tag}.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def fleet(scenario: Path, out: Path, *args: str, env: dict | None = None, plots: bool = False) -> tuple[dict | None, str, float]:
    """One ``stack-fleet run`` (no progress bar); returns (report or None, its last error line, wall seconds)."""
    exe = Path(sys.executable).with_name("stack-fleet")
    cmd = [str(exe), "run", str(scenario), *args, "--out", str(out), "--no-progress", *([] if plots else ["--no-plots"])]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    rep_path = out / "report.json"
    if not rep_path.exists():
        lines = (p.stderr or p.stdout).strip().splitlines()
        return None, lines[-1] if lines else f"no report (exit {p.returncode})", wall
    return json.loads(rep_path.read_text()), "", wall


def setting(flag: str, block: str):
    """An argparse type for ``FLAG KEY=VALUE`` (a ``robot.<block>`` field; VALUE read as YAML)."""
    def parse(s: str) -> tuple[str, object]:
        k, sep, v = s.partition("=")
        if not sep or not k:
            raise argparse.ArgumentTypeError(f"{flag} {s!r}: expected KEY=VALUE (a robot.{block} field)")
        return k, yaml.safe_load(v)
    return parse
