"""A narrow passage: a wall across the way with one gap 1.4 m wide (the robot is 1.0 m across, the guard keeps
0.1 m more each side), 1.3 m off the straight line to the goal, in a closed arena. Every policy of the contract
crosses it and reaches its goal with no contact, one robot each (``stack-fleet bench``, two runs at a time; the
bench's own table, exit codes and run order are checked on the way).

Measured (lock-step, seed 1, 2026-12-07): at the goal after pid 47 s, aina 52 s, qlearn 61 s, drl 69 s, fuzzy 71 s;
the straight way is blocked, so every one of them is stuck at the wall first and goes through on a planned detour
or its own boundary following. With the arena's far wall 2 m behind the goal ``aina`` stopped 0.8 m short of it
(Deng's obstacle term against the attraction); here it is 6 m behind.
"""

from __future__ import annotations

import json

import pytest
from conftest import run_cli, write_scenario

POLICIES = ("pid", "aina", "qlearn", "drl", "fuzzy")
GAP = (1.3, 2.7)  # [m] y of the gap's edges in the wall at x = 5


def narrow_gap() -> dict:
    wall = lambda a, b: {"type": "wall", "from": list(a), "to": list(b), "thickness": 0.2}  # noqa: E731
    return {
        "name": "narrow-gap", "seed": 1, "dt": 0.1, "duration": 150.0,
        "world": {"obstacles": [wall((5, -8), (5, GAP[0])), wall((5, GAP[1]), (5, 8)),  # the wall and its gap
                                wall((-2, 8), (16, 8)), wall((-2, -8), (16, -8)), wall((-2, -8), (-2, 8)),
                                wall((16, -8), (16, 8))]},
        "robot": {"radius": 0.5, "v_max": 1.0, "w_max": 1.0, "comm_range": 10.0,
                  "lidar": {"beams": 180, "fov_deg": 180, "range": 5.0, "noise_std": 0.0}},
        "comm": {"loss": 0.0, "latency_ms": 0},
        "formation": {"leader": 0, "goal": [10.0, 0.0], "slots": {}},
        "robots": [{"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0]}],
        "success": {"goal_tolerance": 0.5, "max_time": 150.0, "no_collisions": True},
        "bench": {"policies": list(POLICIES), "reference": "a gap 1.4 m wide"},
    }


@pytest.mark.fleet
def test_every_policy_crosses_a_gap_just_wider_than_the_robot(tmp_path):
    folder = tmp_path / "scenarios"
    folder.mkdir()
    write_scenario(folder / "narrow-gap.yaml", narrow_gap())
    proc = run_cli(["stack-fleet", "bench", "--scenarios", str(folder), "--jobs", "2", "--out", str(tmp_path / "bench")],
                   timeout=300)
    data = json.loads((tmp_path / "bench" / "bench.json").read_text())
    assert [r["policy"] for r in data["runs"]] == list(POLICIES), proc.stderr  # the scenario's bench.policies, in order
    assert data["skipped"] == []
    table = (tmp_path / "bench" / "bench.md").read_text()
    assert all(f"| narrow-gap | {p} |" in table for p in POLICIES) and "a gap 1.4 m wide" in table
    for run in data["runs"]:
        p = run["policy"]
        rep = json.loads((tmp_path / "bench" / f"narrow-gap-{p}" / "report.json").read_text())
        assert rep["policies"]["0"] == p and rep["crashed"] == []
        assert run["exit"] == (0 if rep["success"] else 1), (run, rep["success"])  # a run's exit code: its verdict
        assert rep["success"] and rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}, (p, rep["success"])
        assert rep["min_obstacle_distance_m"] > 0.0, (p, rep["min_obstacle_distance_m"])
    assert proc.returncode == 0, proc.stderr  # the bench's: 0 when every run met its goal
