"""The course generator (stack.fleet.courses): valid, solvable, deterministic, varied; the held-out seeds refused."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import ROOT, run_fleet, write_scenario
from stack.fleet import bench
from stack.fleet.courses import (DENSITIES, FAMILIES, HELDOUT_SEEDS, HELDOUT_START, LANE_CLEAR, MARGIN, NARROW_GAP,
                                 RADIUS, CourseError, _choose, distance_field, generate, generate_course, main,
                                 random_scenarios, time_budget, unsolvable_reason)
from stack.scenario import load_scenario, parse_scenario

SEEDS = range(0, 8)  # tests use seeds below HELDOUT_START only: generate() refuses the others


def course(seed, **kw):
    assert seed < HELDOUT_START
    return generate_course(seed, **kw)


@pytest.mark.parametrize("density", list(DENSITIES))
def test_valid_and_solvable(tmp_path, density):
    for seed in SEEDS:
        c = course(seed, density=density)
        path = write_scenario(tmp_path / f"{seed}.yaml", c.scenario)
        sc = load_scenario(path)  # the file a user gets, read back by the scenario reader
        assert unsolvable_reason(sc) is None
        assert 3 <= len(sc.robots) <= 8 and sc.formation.goal == (c.length, 0.0)
        assert sc.robots[0].pose == (0.0, 0.0, 0.0) and all(r.pose[0] <= 0.5 for r in sc.robots)
        assert sc.duration == sc.success.max_time == time_budget(c.length)
        lo, hi = DENSITIES[density].per_10m
        fld = c.length - max(-r.pose[0] for r in sc.robots) - 9.0  # the field, about: FIELD_START .. goal - depth - GOAL_CLEAR
        assert c.obstacles >= max(1, math.floor(lo * fld / 10) - 1) and c.obstacles <= math.ceil(hi * (fld + 1) / 10)
        kinds = {o.type for o in sc.obstacles}
        assert "wall" in kinds and kinds & {"cylinder", "box"}


def _corridor(gap: float | None) -> dict:
    """Three robots in a 10 m corridor; a wall across it at x = 8 with a gap of ``gap`` m at y = 0 (None: no gap)."""
    walls = [{"type": "wall", "from": [-6, 5], "to": [20, 5]}, {"type": "wall", "from": [-6, -5], "to": [20, -5]}]
    if gap is None:
        walls.append({"type": "wall", "from": [8, -5], "to": [8, 5], "thickness": 0.3})
    else:
        walls += [{"type": "wall", "from": [8, -5], "to": [8, -gap / 2], "thickness": 0.3},
                  {"type": "wall", "from": [8, gap / 2], "to": [8, 5], "thickness": 0.3}]
    return {"dt": 0.1, "world": {"obstacles": walls}, "robot": {"radius": RADIUS},
            "formation": {"leader": 0, "goal": [16.0, 0.0], "slots": {1: {"L": 2.5, "psi_deg": 135}, 2: {"L": 2.5, "psi_deg": -135}}},
            "robots": [{"id": 0, "pose": [0, 0, 0]}, {"id": 1, "pose": [-1.77, 1.77, 0]}, {"id": 2, "pose": [-1.77, -1.77, 0]}]}


def test_checker_rejects_what_cannot_be_passed():
    assert unsolvable_reason(parse_scenario(_corridor(2.0))) is None
    assert "no path" in unsolvable_reason(parse_scenario(_corridor(None)))  # a wall with no gap
    assert "no path" in unsolvable_reason(parse_scenario(_corridor(2 * RADIUS + MARGIN - 0.2)))  # narrower than the path
    bad = _corridor(2.0)
    bad["world"]["obstacles"].append({"type": "cylinder", "x": -1.77, "y": 1.77, "radius": 0.3})
    assert "robot 1 starts" in unsolvable_reason(parse_scenario(bad))
    bad = _corridor(2.0)
    bad["robots"][2]["pose"] = [-1.77, 1.1, 0]
    assert "start 0.67 m apart" in unsolvable_reason(parse_scenario(bad))
    bad = _corridor(2.0)  # a goal slot inside an obstacle
    bad["world"]["obstacles"].append({"type": "box", "x": 14.2, "y": 1.8, "size_x": 1.0, "size_y": 1.0})
    assert "robot 1's start to its goal" in unsolvable_reason(parse_scenario(bad))
    # a generated course with its passage closed
    c = course(3, density="high")
    closed = dict(c.scenario, world={"obstacles": c.scenario["world"]["obstacles"] + [
        {"type": "wall", "from": [c.passages[0]["x"], -c.half_width], "to": [c.passages[0]["x"], c.half_width]}]})
    assert "no path" in unsolvable_reason(parse_scenario(closed))


def test_deterministic_per_seed_and_different_across_seeds(tmp_path):
    assert generate(5) == generate(5)
    assert generate(5, robots=4, density="high") == generate(5, robots=4, density="high")
    outs = [tmp_path / "a.yaml", tmp_path / "b.yaml"]
    for out in outs:
        assert main(["--seed", "7", "--density", "medium", "--out", str(out)]) == 0
    assert outs[0].read_bytes() == outs[1].read_bytes()
    worlds = [yaml.safe_dump(generate(s, density="low")["world"]) for s in range(10)]
    assert len(set(worlds)) == 10
    assert len({generate(s)["name"] for s in range(6)}) == 6


def test_every_family_and_density():
    for f in FAMILIES:
        for d in DENSITIES:
            c = course(11, formation=f, density=d)
            assert (c.family, c.density) == (f, d)
            slots = parse_scenario(c.scenario).formation.slots
            pts = np.array([(0.0, 0.0)] + [(s.L * math.cos(s.psi), s.L * math.sin(s.psi)) for s in slots.values()])
            dist = np.hypot(*(pts[:, None] - pts[None]).transpose(2, 0, 1))[np.triu_indices(len(pts), 1)]
            assert dist.min() == pytest.approx(c.spacing, abs=2e-3) and dist.min() >= 2.0 - 1e-3
            assert max(s.L for s in slots.values()) <= 8.0 + 1e-3
    drawn = [_choose(np.random.default_rng(s), None, None, None) for s in range(60)]
    assert {f for _, f, _ in drawn} == set(FAMILIES)
    assert {d for _, _, d in drawn} == set(DENSITIES)
    assert {n for n, _, _ in drawn} == set(range(3, 9))
    with pytest.raises(CourseError, match="a column holds at most 5 robots"):
        generate(1, robots=8, formation="column")


def test_narrow_passages_are_narrower_than_the_formation():
    narrow = 0
    for seed in range(12):
        c = course(seed, density="high")
        p = next(p for p in c.passages if p["kind"] == "passage")
        blocks = sorted((o for o in c.scenario["world"]["obstacles"] if o["type"] == "box" and o["x"] == p["x"]),
                        key=lambda o: o["y"])
        assert len(blocks) == 2
        gap = (blocks[1]["y"] - blocks[1]["size_y"] / 2) - (blocks[0]["y"] + blocks[0]["size_y"] / 2)
        assert gap == pytest.approx(p["gap"], abs=0.01) and gap > 2 * RADIUS + MARGIN
        if c.width > NARROW_GAP[0] + 0.3:
            assert p["narrow"] and gap < c.width
            narrow += 1
        else:  # a formation one robot wide (a column) passes anything that is solvable
            assert c.family == "column"
    assert narrow >= 8


def test_low_density_keeps_the_lane_free():
    for seed in SEEDS:
        sc = parse_scenario(generate(seed, density="low"))
        xs = np.linspace(-10, sc.formation.goal[0], 400)
        for r in sc.robots:
            clear = distance_field(sc.obstacles, xs, np.full_like(xs, r.pose[1]))
            assert clear.min() >= RADIUS + LANE_CLEAR - 0.35  # starts are up to 0.3 m off the slot


def test_heldout_seeds_refused():
    assert HELDOUT_SEEDS.start == HELDOUT_START == 1_000_000 and len(HELDOUT_SEEDS) == 1000
    for seed in (HELDOUT_START, HELDOUT_START + 999):
        with pytest.raises(CourseError, match="held out"):
            generate(seed)
    with pytest.raises(CourseError, match="not a held-out seed"):
        generate(3, purpose="heldout")
    assert generate(HELDOUT_START + 1000)["seed"] == HELDOUT_START + 1000  # past the range: allowed
    assert generate(HELDOUT_START, density="low", purpose="heldout")["seed"] == HELDOUT_START


def test_time_budget_scales_with_length():
    assert time_budget(40.0) == 160.0 and time_budget(20.0) == 90.0
    short, long_ = course(2, density="low", length=20.0), course(2, density="low", length=60.0)
    assert short.scenario["duration"] < long_.scenario["duration"]
    with pytest.raises(CourseError, match="--length"):
        generate(2, density="high", length=10.0)


def _exit_code(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as e:  # argparse's own errors
        return e.code


@pytest.mark.parametrize("args, message", [
    (["--seed", "1", "--robots", "9"], "--robots: expected 3..8, got 9"),
    (["--seed", "1", "--formation", "blob"], "--formation: expected one of wedge"),
    (["--seed", "1", "--density", "dense"], "--density: expected one of low, medium, high"),
    (["--seed", "1000000"], "held out"),
    (["--seed", "-1"], "--seed: expected an integer >= 0"),
    (["--robots", "4"], "required: --seed"),
])
def test_cli_bad_input_is_one_line_exit_2(tmp_path, capsys, args, message):
    assert _exit_code(args + ["--out", str(tmp_path / "c.yaml")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c.yaml").exists()


def test_cli_as_a_module(tmp_path):
    out = tmp_path / "c.yaml"
    p = subprocess.run([sys.executable, "-m", "stack.fleet.courses", "--seed", "4", "--robots", "5", "--formation",
                        "diamond", "--density", "high", "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    assert out.read_text().startswith("# generated by stack.fleet.courses: seed 4, 5 robots in formation diamond")
    sc = load_scenario(out)
    assert len(sc.robots) == 5 and unsolvable_reason(sc) is None
    p = subprocess.run([sys.executable, "-m", "stack.fleet.courses", "--seed", "4", "--out", str(tmp_path)],
                       capture_output=True, text=True, cwd=ROOT)
    assert p.returncode == 2 and "is a folder" in p.stderr


def test_random_scenarios_and_bench_random(tmp_path, monkeypatch):
    cs = random_scenarios(3, first_seed=10, density="medium")
    assert [c.seed for c in cs] == [10, 11, 12] and all(c.density == "medium" for c in cs)
    with pytest.raises(CourseError):
        random_scenarios(0)
    with pytest.raises(CourseError, match="held out"):
        random_scenarios(2, first_seed=HELDOUT_START - 1)
    seen = {}
    monkeypatch.setattr(bench, "main", lambda folder, out, seed=None, policies=None, engine=None: seen.update(
        files=sorted(p.name for p in Path(folder).glob("*.yaml")), policies=policies) or 0)
    (tmp_path / "courses").mkdir()
    (tmp_path / "courses" / "stale.yaml").write_text("old")
    assert bench.random_bench(2, tmp_path, first_seed=20, density="low", policies=["pid"]) == 0
    assert seen == {"files": sorted(f"{generate(s, density='low')['name']}.yaml" for s in (20, 21)), "policies": ["pid"]}
    assert bench.random_bench(1, tmp_path, first_seed=HELDOUT_START) == 2


@pytest.mark.fleet
def test_pid_fleet_passes_a_short_generated_course(tmp_path):
    """One generated course in the fleet (one process per robot): three robots, `low`, a 20 m corridor."""
    c = course(1, robots=3, density="low", length=20.0)
    path = write_scenario(tmp_path / "course.yaml", c.scenario)
    proc, rep = run_fleet(path, tmp_path / "run", "--policy", "pid", "--no-plots", timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert rep["success"] and rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    assert rep["leader_time_to_goal_s"] < c.scenario["success"]["max_time"] and rep["formation_error_rms_m"] < 1.0


@pytest.mark.fleet
@pytest.mark.parametrize("policy, density", [("drl", "medium"), ("qlearn", "medium"), ("aina", "low")])
def test_each_avoiding_policy_passes_a_short_generated_course(tmp_path, policy, density):
    """Each obstacle-avoiding policy on one generated course in the fleet: three robots, a 20 m corridor; at
    `medium` obstacles anywhere and a wall across it. `aina` steers locally (Deng's immune network toward the
    goal): this course's cross wall, its gap off the leader's line, traps its leader until the stuck detector
    gives up, so it runs the `low` course (the held-out table in the README says how often that happens)."""
    c = course(5, robots=3, density=density, length=20.0)
    assert c.obstacles >= 2 and (c.passages or density == "low")
    path = write_scenario(tmp_path / "course.yaml", c.scenario)
    proc, rep = run_fleet(path, tmp_path / "run", "--policy", policy, "--no-plots", "--no-record", timeout=300)
    assert proc.returncode == 0, (policy, proc.stderr[-2000:])
    assert rep["success"] and rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    assert rep["min_obstacle_distance_m"] > c.scenario["robot"]["radius"]
    assert all(r["guard_caps"] is not None for r in rep["robots"].values())
