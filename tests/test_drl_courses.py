"""Stage 3 of ``stack-train drl`` (stack/train/course_scenes.py): training scenes cut from generated courses, the
curriculum over density and robot count, robots a scene has no use for parked and inactive, a short real run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stack.train.course_scenes import LEVELS, CourseScenes, heldout_clash, level, parked
from stack.train.drlworld import DrlWorld, WorldConfig, obstacle_distance

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pool() -> CourseScenes:
    return CourseScenes(18, first_seed=40)  # every density, 3-8 robots


def test_the_curriculum_widens_by_thirds(pool):
    assert level(0.0) == LEVELS[0] and level(0.5) == LEVELS[1] and level(0.99) == level(1.0) == LEVELS[2]
    rng = np.random.default_rng(1)
    for progress, (densities, most) in ((0.1, LEVELS[0]), (0.5, LEVELS[1]), (0.9, LEVELS[2])):
        pool.progress = progress
        counts = [int((~parked(pool(rng)[0])).sum()) for _ in range(12)]
        assert 3 <= min(counts) and max(counts) <= most
    assert {c.density for c in pool.pool} == {"low", "medium", "high"} and max(c.robots for c in pool.pool) == 8


def test_a_scene_is_a_clear_stretch_of_its_course_with_the_targets_down_the_corridor(pool):
    pool.progress = 1.0
    rng = np.random.default_rng(2)
    for _ in range(10):
        starts, yaws, goals, circles, boxes = pool(rng)
        here = ~parked(starts)
        s, g = starts[here], goals[here]
        shift = g - s
        assert np.allclose(shift, shift[0]) and 5.0 <= shift[0, 0] <= 14.0 and shift[0, 1] == 0.0  # one common shift
        assert obstacle_distance(s[:, 0], s[:, 1], circles, boxes).min() >= 0.5  # no robot starts in an obstacle
        assert len(starts) == len(goals) == len(yaws) == 8 and parked(goals).tolist() == parked(starts).tolist()


def test_parked_robots_never_act_and_the_trained_robot_is_in_the_scene(pool):
    pool.progress = 0.0  # 3-4 robots: at least four parked in a world of 8
    w = DrlWorld(4, 3, seed=0, scenes=pool, cfg=WorldConfig(robots=8, max_circles=24, max_boxes=24, max_steps=20))
    assert (w.present.sum(axis=1) <= 4).all() and (~w.present.any(axis=0)).any()
    assert w.present[np.arange(4), w.trained].all()
    assert not w.active[~w.present].any()
    from stack.policies.drl.observation import ACTIONS

    for _ in range(10):
        _, arrived, collided, _, _ = w.step(np.full((4, 8), 7), ACTIONS)
        assert not (arrived | collided)[~w.present].any()
        assert (w.x[~w.present] > 1e3).all()  # still parked: a zero command
    assert (w.observe()["n_nb"][w.present] <= 3).all()  # a parked robot is nobody's neighbour


def test_training_and_held_out_seeds_do_not_mix():
    assert heldout_clash(0, 240) is None and heldout_clash(999_990, 20) is not None
    with pytest.raises(ValueError, match="held-out"):
        CourseScenes(5, first_seed=1_000_000)
    r = subprocess.run([sys.executable, "-m", "stack.train", "drl", "--stage", "3", "--course-seed", "999990",
                        "--courses", "20"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 2 and "--course-seed 999990" in r.stderr and "Traceback" not in r.stderr


def test_a_short_stage_3_run_trains_from_the_shipped_weights_and_evaluates(tmp_path):
    """Real courses, the real network and replay: 6 episodes, 2 environments (the hour-long run is a command)."""
    out = tmp_path / "drl3"
    r = subprocess.run([sys.executable, "-m", "stack.train", "drl", "--stage", "3", "--episodes", "6", "--envs", "2",
                        "--courses", "6", "--max-steps", "40", "--learn-start", "32", "--batch", "16",
                        "--eval-episodes", "3", "--init", "stack/policies/drl/weights/drl.pt", "--out", str(out),
                        "--no-progress", "--no-plots"], capture_output=True, text=True, cwd=ROOT, timeout=240)
    assert r.returncode == 0, r.stderr[-2000:]
    d = json.loads((out / "drl.json").read_text())
    assert d["episodes"] >= 6 and d["gradient_steps"] > 0 and (out / "drl.pt").exists()
    assert d["job"]["stage"] == 3 and d["evaluation"]["drl.pt"]["robots"] == 8
