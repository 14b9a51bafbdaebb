"""Stage 3 of ``stack-train drl`` (stack/train/course_scenes.py): training scenes cut from generated courses, the
curriculum over density and robot count, robots a scene has no use for parked and inactive, a short real run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

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


# --- follow scenes (--follow): the targets move as the fleet's do ---------------------------------------------------
def _follow_world(pool, n=3, **cfg) -> DrlWorld:
    pool.progress = 0.0
    return DrlWorld(n, 3, seed=3, scenes=pool, cfg=WorldConfig(robots=8, max_circles=24, max_boxes=24, max_steps=50,
                                                            follow=True, **cfg))


def test_a_followers_target_is_its_slot_round_the_leader_where_it_is_now():
    from stack.models.geometry import slot_position
    from stack.policies.drl.observation import ACTIONS

    pool = CourseScenes(6, first_seed=40, follow=True)
    w = _follow_world(pool)
    slot, x0 = w.slot.copy(), w.x[:, 0].copy()
    here = w.present.copy()
    here[:, 0] = False
    assert np.allclose(np.stack([w.gx, w.gy], -1)[here], np.stack([w.x, w.y], -1)[here])  # they start on their slots
    a = np.full((3, 8), 12)  # everyone straight on at 1 m/s (index 5 * 2 + 2)
    for _ in range(5):
        w.step(a, ACTIONS)
    for n in range(3):
        for r in np.flatnonzero(here[n]):
            L, psi = float(np.hypot(*slot[n, r])), float(np.arctan2(slot[n, r, 1], slot[n, r, 0]))
            p = slot_position((w.x[n, 0], w.y[n, 0]), SimpleNamespace(L=L, psi=psi))
            assert np.allclose((w.gx[n, r], w.gy[n, r]), p, atol=1e-9)  # eq. (3) round the leader now
    assert np.all(w.x[:, 0] - x0 > 0.2)  # the leader drove on, and the targets with it


def test_a_follower_on_its_moving_slot_does_not_arrive_until_its_leader_has_stopped():
    from stack.policies.drl.observation import ACTIONS

    pool = CourseScenes(6, first_seed=40, follow=True)
    w = _follow_world(pool, n=1)
    a = np.full((1, 8), 12)
    a[0, 1:] = 2  # the followers stand still on their slots (v 0, w 0) while the leader drives off
    _, arrived, _, _, _ = w.step(a, ACTIONS)
    assert not arrived[0, 1:].any()  # on its slot, but the slot moves on
    w.active[0, 0] = False  # the leader stops (as when it arrives): the slots stand still
    w.gx[0, 1:], w.gy[0, 1:] = w.x[0, 1:], w.y[0, 1:]
    w.slot[0, 1:] = np.stack([w.x[0, 1:] - w.x[0, 0], w.y[0, 1:] - w.y[0, 0]], -1)
    _, arrived, _, _, _ = w.step(np.full((1, 8), 2), ACTIONS)
    assert arrived[0, 1:][w.present[0, 1:]].all()


def test_the_leader_of_a_follow_scene_drives_at_the_agents_leader_speed():
    from stack.agents.decision import DecisionLayer

    pool = CourseScenes(6, first_seed=40, follow=True)
    w = _follow_world(pool, n=2)
    w.x[0, 1] = w.x[0, 0] - 7.0  # a follower 7 m behind: eq. (20) gives 5/7; the hold 1 (< 8 m)
    w.y[0, 1] = w.y[0, 0]
    w.x[1, 1], w.y[1, 1] = w.x[1, 0] - 9.0, w.y[1, 0]  # 9 m: 5/9 of it, the hold a third of that
    v = w._leader_speed(np.array([1.0, 1.0]))
    for n in range(2):
        d = float(np.max(np.hypot(w.x[n] - w.x[n, 0], w.y[n] - w.y[n, 0])[w.present[n]]))
        assert v[n] == pytest.approx(DecisionLayer.leader_speed(1.0, d, hold=(0.8, 0.95)))
    assert v[0] == pytest.approx(5 / 7) and v[1] == pytest.approx(5 / 9 * (9.5 - 9.0) / 1.5)


def test_a_robot_that_stopped_holds_the_leader_no_longer_and_a_held_leader_is_not_stalled():
    """The fleet's hold gives up on a robot that does not come; a training scene whose robot collided or stalled must
    not leave its leader waiting for ever (nor end the leader's episode as standing still while the hold stops it)."""
    from stack.policies.drl.observation import ACTIONS

    pool = CourseScenes(6, first_seed=40, follow=True)
    w = _follow_world(pool, n=2, stall_steps=5)
    for n in range(2):
        w.x[n, 1], w.y[n, 1] = w.x[n, 0] - 9.6, w.y[n, 0]  # beyond the hold's stop (9.5 m): the leader stands
    w.active[1, 1] = False  # in scene 1 that robot has stopped (collided)
    v = w._leader_speed(np.array([1.0, 1.0]))
    assert v[0] == 0.0 and w.held[0]  # held for the robot that still drives
    assert v[1] > 0.0  # the stopped one holds no one
    w.active[1, 2:] = False  # scene 1: only the leader left; scene 0: everyone stands but the held leader
    a = np.full((2, 8), 2)
    a[:, 0] = 12
    for _ in range(8):
        w.x[0, 1] = w.x[0, 0] - 9.6  # the far robot stays far: the leader stays held
        w.step(a, ACTIONS)
        assert not w.stalled[:, 0].any()
    assert w.x[1, 0] > w.x[1, 1] + 9.6 + 0.5  # scene 1's leader drove on


def test_a_robot_waiting_on_its_target_is_not_stalled():
    from stack.policies.drl.observation import ACTIONS

    pool = CourseScenes(6, first_seed=40, follow=True)
    w = _follow_world(pool, n=1, stall_steps=5)
    w.active[0, 0] = False  # the leader stands: the followers wait on their slots, which do not move
    for _ in range(8):
        w.step(np.full((1, 8), 2), ACTIONS)
    assert not w.stalled.any()


def test_follow_is_a_stage_3_flag():
    r = subprocess.run([sys.executable, "-m", "stack.train", "drl", "--stage", "2", "--follow"], capture_output=True,
                       text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 2 and "--follow" in r.stderr and "Traceback" not in r.stderr


def test_a_run_cut_by_time_still_goes_through_the_whole_schedule():
    """--max-minutes: epsilon and the curriculum follow the time where it runs ahead of the episodes."""
    import time

    from stack.train.drl import DrlJob, _Training

    job = DrlJob(stage=3, episodes=8000, eps_start=0.2, eps_end=0.02, eps_fraction=0.5, max_minutes=10.0)
    t = _Training.__new__(_Training)
    t.job, t.episode, t.t0 = job, 400, time.monotonic() - 7 * 60.0  # 5 % of the episodes, 70 % of the time
    assert t.done() == pytest.approx(0.7, abs=0.01)
    assert job.epsilon(400, t.done()) == pytest.approx(0.02)  # past eps_fraction of the time: at the floor
    assert job.epsilon(400) == pytest.approx(0.2 - 0.18 * 0.1)  # by episodes alone: 10 % of the way
    assert level(t.done()) == level(0.9)  # the last third of the curriculum: every density
    t.job = DrlJob(stage=3, episodes=8000)  # no time limit: the episodes alone
    assert t.done() == pytest.approx(0.05)


def test_the_cached_reachability_agrees_with_the_windowed_flood_fill(pool):
    """A scene's reachability check uses the course's free cells computed once; it answers as the flood fill
    over its own window does, but for cells cut differently at an obstacle's edge (the grids' origins differ)."""
    from stack.train.course_scenes import REACH_CELL
    from stack.train.drlworld import reachable

    rng = np.random.default_rng(4)
    agree = total = blocked = 0
    for c in pool.pool[:12]:
        for _ in range(6):
            starts = c.offsets + [float(rng.uniform(0.0, max(c.length - pool.shift[1], 0.0))), 0.0]
            goals = starts + [float(rng.uniform(*pool.shift)), 0.0]
            for s, g in zip(starts, goals):
                want = reachable(s, g, c.circles, c.boxes, c.radius, cell=REACH_CELL)
                agree += pool._reach(c, s, g) == want
                blocked += not want
                total += 1
    assert c.free is not None and total >= 200
    assert blocked > 0 and agree >= 0.97 * total, (agree, total, blocked)
