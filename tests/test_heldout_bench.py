"""bench/heldout.py's plan and table, without running fleets: which runs on which file, in which order, and how
rows become the table (the runs themselves are `stack-fleet run`, tested elsewhere)."""

from __future__ import annotations

import sys

import pytest
from conftest import ROOT

sys.path.insert(0, str(ROOT / "bench"))

import heldout  # noqa: E402

from stack.fleet.courses import HELDOUT_START  # noqa: E402
from stack.scenario import load_scenario  # noqa: E402


def test_plan_lists_every_policy_where_its_course_allows_and_drl_alone_on_a_bare_copy(tmp_path):
    tasks = heldout.plan(2, ["low", "high"], ["drl", "pid", "drl-alone"], tmp_path)
    got = [(t["policy"], t["density"], t["seed"]) for t in tasks]
    assert ("pid", "high", HELDOUT_START) not in got and ("pid", "low", HELDOUT_START) in got  # pid: the free lane only
    assert {t["seed"] for t in tasks} == {HELDOUT_START, HELDOUT_START + 1}
    alone = next(t for t in tasks if t["policy"] == "drl-alone")
    plain = next(t for t in tasks if t["policy"] == "drl" and t["density"] == alone["density"] and t["seed"] == alone["seed"])
    a, p = load_scenario(alone["file"]), load_scenario(plain["file"])
    assert a.obstacles == p.obstacles and [r.pose for r in a.robots] == [r.pose for r in p.robots]
    assert all(not r.guard.enabled and not r.settings["drl"].shield for r in a.robots)
    assert all(r.guard is None for r in p.robots)  # the plain course keeps the defaults: guard and shield on
    assert alone["out"].endswith(f"drl-alone/{alone['density']}/{alone['seed']}")


def test_arrival_tasks_join_the_table_as_their_own_density(tmp_path):
    tasks = heldout.plan_arrival(2, ["fuzzy", "fuzzy-lstm"], tmp_path)
    assert [(t["policy"], t["seed"]) for t in tasks] == [("fuzzy", HELDOUT_START), ("fuzzy-lstm", HELDOUT_START),
                                                        ("fuzzy", HELDOUT_START + 1), ("fuzzy-lstm", HELDOUT_START + 1)]
    assert all(t["density"] == "arrival" and load_scenario(t["file"]).coordination == "arrival_time" for t in tasks)
    reps = [{"success": True, "collisions": {"robot_robot": 0, "robot_obstacle": 0}, "arrival_spread_steps": 4},
            {"success": False, "collisions": {"robot_robot": 1, "robot_obstacle": 0}, "arrival_spread_steps": 40},
            {"success": True, "collisions": {"robot_robot": 0, "robot_obstacle": 0}, "arrival_spread_steps": 8},
            None]
    rows = [heldout.row(t, r, "" if r else "crashed", 1.0) for t, r in zip(tasks, reps)]
    assert [r["outcome"] for r in rows] == ["success", "collision", "success", "error"]
    table = heldout.aggregate(rows, ["fuzzy", "fuzzy-lstm"], ["arrival"])
    fz, lstm = table
    assert (fz["runs"], fz["success"], fz["arrival_spread_steps"], fz["collision_runs"]) == (2, 1.0, 6.0, 0)
    assert (lstm["success"], lstm["collision_runs"], lstm["robot_robot"], lstm["errors"]) == (0.0, 1, 1, 1)
    md = heldout.markdown(table, range(HELDOUT_START, HELDOUT_START + 2), "python bench/heldout.py --arrival 2")
    assert "| fuzzy | arrival | 2 | 100 % |" in md and "arrival_spread_steps" in md


def test_a_later_table_takes_the_seeds_after_the_spent_ones(tmp_path, capsys):
    tasks = heldout.plan(2, ["low"], ["pid"], tmp_path, skip=34)
    assert [t["seed"] for t in tasks] == [HELDOUT_START + 34, HELDOUT_START + 35]
    assert [t["seed"] for t in heldout.plan_arrival(1, ["fuzzy"], tmp_path, skip=34)] == [HELDOUT_START + 34]
    for flags, msg in ((["--first-seed", "5"], "--first-seed 5: expected a held-out seed, 1000000..1000999"),
                       (["--first-seed", "1000990", "--courses", "20"], "expected 0..10 each from seed 1000990")):
        with pytest.raises(SystemExit) as e:
            heldout.main([*flags, "--out", str(tmp_path / "x")])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert msg in err, err


def test_tuning_courses_come_from_the_tuning_seeds_and_never_from_the_held_out_ones(tmp_path, capsys):
    from stack.fleet.courses import TUNE_SEEDS

    tasks = heldout.plan(2, ["low"], ["pid"], tmp_path, skip=600, seeds=TUNE_SEEDS)
    assert [t["seed"] for t in tasks] == [600, 601]
    for flags, msg in ((["--first-seed", str(HELDOUT_START)], f"--first-seed {HELDOUT_START}: expected a tuning seed, 0..999"),
                       (["--arrival", "3"], "arrival-time tasks come from held-out seeds only")):
        with pytest.raises(SystemExit) as e:
            heldout.main(["--tuning", *flags, "--out", str(tmp_path / "x")])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert msg in err, err
    assert "Tuning seeds 600..601" in heldout.markdown([], range(600, 602), "c", "Tuning")


def test_drl_weights_go_to_both_drl_kinds_and_nothing_else(tmp_path, capsys):
    w = ROOT / "stack" / "policies" / "drl" / "weights" / "drl.pt"
    tasks = heldout.plan(1, ["medium"], ["drl", "drl-alone", "aina"], tmp_path, drl_weights=w)
    assert not next(t for t in tasks if t["policy"] == "aina")["file"].endswith("-weights.yaml")  # its own file
    tasks = [t for t in tasks if t["policy"] != "aina"]
    by = {t["policy"]: load_scenario(t["file"]) for t in tasks}
    assert all(r.settings["drl"].weights == str(w) for p in ("drl", "drl-alone") for r in by[p].robots)
    assert all(r.settings["drl"].shield for r in by["drl"].robots)  # the shield stays on for plain drl
    assert all(not r.settings["drl"].shield and not r.guard.enabled for r in by["drl-alone"].robots)
    with pytest.raises(SystemExit) as e:
        heldout.main(["--drl-weights", str(tmp_path / "none.pt"), "--out", str(tmp_path / "x")])
    assert e.value.code == 2 and "--drl-weights" in capsys.readouterr().err


def test_drl_set_reaches_both_drl_kinds_and_a_bad_setting_is_one_line(tmp_path, capsys):
    tasks = heldout.plan(1, ["low"], ["drl", "drl-alone", "pid"], tmp_path, drl_set={"centre_heading": False})
    by = {t["policy"]: load_scenario(t["file"]) for t in tasks}
    assert all(not r.settings["drl"].centre_heading for p in ("drl", "drl-alone") for r in by[p].robots)
    assert all(r.settings["drl"].shield for r in by["drl"].robots)
    assert not next(t for t in tasks if t["policy"] == "pid")["file"].endswith("-weights.yaml")
    for flag, msg in (("bogus=1", "--drl-set bogus: not a robot.drl setting"), ("shield", "expected KEY=VALUE"),
                      ("shield_margin=-1", "shield_margin: must be >= 0")):
        with pytest.raises(SystemExit) as e:
            heldout.main(["--tuning", "--drl-set", flag, "--out", str(tmp_path / "x")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and msg in err and "Traceback" not in err, err


def test_each_run_waits_for_a_slow_agent_and_the_table_counts_the_runs_that_still_went_on(tmp_path, monkeypatch, capsys):
    """A loaded machine makes an agent late, not a policy fail: every run gets --lockstep-timeout (20 s by default,
    not stack-fleet's 2 s), and runs whose world still went on without an agent are counted per row."""
    tasks = heldout.plan(2, ["low"], ["pid"], tmp_path)
    seen = []

    def fake_jobs(jobs, eng, desc=""):
        seen.extend(j.args[2] for j in jobs)
        return [({"success": True, "late_steps": n, "collisions": {}}, "", 1.0) for n in (0, 3)]

    monkeypatch.setattr(heldout, "run_jobs", fake_jobs)
    monkeypatch.setattr(heldout, "report_of", lambda r: r)
    rows = heldout.run_all(tasks, None, False)
    assert seen == [("--policy", "pid", "--lockstep-timeout", "20")] * 2
    assert heldout.aggregate(rows, ["pid"], ["low"])[0]["late_step_runs"] == 1
    heldout.run_all(tasks, None, False, lockstep_timeout=7.5)
    assert seen[-1][-1] == "7.5"
    with pytest.raises(SystemExit) as e:
        heldout.main(["--lockstep-timeout", "0", "--out", str(tmp_path / "x")])
    assert e.value.code == 2 and "--lockstep-timeout 0: expected > 0 s" in capsys.readouterr().err
