"""What the fleet benchmarks share: a scenario with per-robot policy settings over it, and the runs'
engine (``stack.fleet.jobs``: ``--jobs N`` here or ``--engine dask``; each run one ``stack-fleet run``
process, ``stack.fleet.jobs.cli_task``, its report read back)."""

from __future__ import annotations

import argparse
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


def engine(ap: argparse.ArgumentParser, a: argparse.Namespace):
    """The ``--jobs/--engine/--scheduler`` flags (``stack.fleet.jobs.add_engine_args``) as an engine; bad ones: ap.error."""
    from stack.fleet.jobs import EngineError, engine_config

    try:
        return engine_config(a)
    except EngineError as e:
        ap.error(str(e))


def report_of(result) -> tuple[dict | None, str, float]:
    """A ``cli_task`` result, or a failed run's (no report, why, 0 s)."""
    from stack.fleet.jobs import JobFailed

    return (None, result.message, 0.0) if isinstance(result, JobFailed) else result


def setting(flag: str, block: str):
    """An argparse type for ``FLAG KEY=VALUE`` (a ``robot.<block>`` field; VALUE read as YAML)."""
    def parse(s: str) -> tuple[str, object]:
        k, sep, v = s.partition("=")
        if not sep or not k:
            raise argparse.ArgumentTypeError(f"{flag} {s!r}: expected KEY=VALUE (a robot.{block} field)")
        return k, yaml.safe_load(v)
    return parse
