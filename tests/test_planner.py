"""Plans beside the control step (``stack.planning.runner``): a slow planner never holds a step.

The test double ``tests/plugins/slowplan_policy.py`` asks for a plan every second that computes for 2 s of pure
Python (the GIL held, as a real Python planner holds it). In a real-time fleet its control steps stay under
dt / 2 and it drives on its last plan; in lock-step a plan drives from the step after the one that asked,
however long it computed, so two runs agree to the bit; a real-time run's adoption steps, logged, replay.
"""

from __future__ import annotations

import math
import random
import sys
import time
from pathlib import Path

import pytest
from conftest import run_fleet, scenario_dict, write_scenario

from stack.agents import steplog
from stack.agents.step import OdomSample, StepInputs, StepPipeline
from stack.comm.messages import Scan
from stack.planning.runner import PlanRunner, ScriptedRunner, ThreadRunner
from stack.policies import POLICIES
from stack.replay.run import differing
from stack.scenario import parse_scenario

PLUGINS = Path(__file__).resolve().parent / "plugins"


@pytest.fixture
def slowplan(monkeypatch):
    """The double registered by name, for this process and the fleets it starts."""
    monkeypatch.syspath_prepend(str(PLUGINS))
    monkeypatch.setenv("PYTHONPATH", str(PLUGINS) + ":" + ":".join(sys.path))
    monkeypatch.setenv("FORMATION_STACK_PLUGINS", "slowplan_policy")
    POLICIES.reload()
    import slowplan_policy

    yield slowplan_policy
    monkeypatch.undo()
    sys.modules.pop("slowplan_policy", None)
    POLICIES.reload()


def _alone(goal=(5.0, 0.0)) -> dict:
    d = scenario_dict(duration=7.0)
    d["name"] = "slow-planner"
    d["formation"] = {"leader": 0, "goal": list(goal), "slots": {}}
    d["world"] = {"obstacles": []}
    d["robots"] = [{"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0]}]
    d["success"] = {"goal_tolerance": 0.3, "max_time": 7.0, "no_collisions": True}
    return d


@pytest.mark.fleet
def test_a_two_second_planner_never_holds_a_real_time_step(slowplan, tmp_path):
    path = write_scenario(tmp_path / "slow.yaml", _alone())
    proc, rep = run_fleet(path, tmp_path / "out", "--policy", "slowplan", "--realtime", "--no-plots", timeout=120)
    assert rep is not None, proc.stderr
    plans = rep["planning"]["0"]
    assert plans["mode"] == "real time" and plans["adopted"] >= 2, plans
    assert plans["ms_max"] >= 0.9 * slowplan.PLAN_S * 1e3, plans  # the plans took their 2 s...
    compute = rep["control_compute_ms"]
    assert compute["p99"] < 0.5 * rep["dt"] * 1e3, (compute, plans)  # ...and no step waited for them
    robot = rep["robots"]["0"]
    assert robot["path_length_m"] > 1.0, robot  # it drove on its last plan between plans


def _inputs(k: int, dt: float, v: float, w: float, beams: int) -> StepInputs:
    t = k * dt
    scan = Scan(id=0, step=k, stamp=t, angle_min=-math.pi / 2, angle_increment=math.pi / (beams - 1), range_max=5.0,
                ranges=[5.0] * beams)
    return StepInputs(step=k, t=t, t_run=t, now=t, odometry=(OdomSample(v=v, w=w, t=t),), scan=scan, scan_t=t)


class _Jittered(ThreadRunner):
    """Every plan computes for a random extra 0-60 ms (another machine, another load)."""

    def __init__(self, lockstep_steps, seed):
        super().__init__(lockstep_steps)
        self.rng = random.Random(seed)

    def _start(self, job):
        fn, extra = job.fn, self.rng.uniform(0.0, 0.06)
        job.fn = lambda: (time.sleep(extra), fn())[1]
        super()._start(job)


def _drive(runner: PlanRunner, steps: int, plans=None):
    """The double's pipeline closed over its own commands (odometry = last command): outputs and adopted tickets."""
    sc = parse_scenario(_alone())
    pl = StepPipeline(sc, 0, policy="slowplan")
    pl.use_planner(runner)
    v = w = 0.0
    outs, adopted = [], []
    for k in range(steps):
        inp = _inputs(k, sc.dt, v, w, sc.robot(0).lidar.beams)
        if plans is not None:
            inp = StepInputs(**{**inp.__dict__, "plans": plans[k]})
        out = pl.step(inp)
        outs.append(steplog.out_of(out, pl))
        adopted.append(tuple(pl.planner.adopted_now))
        v, w = out.v, out.w
        time.sleep(0.01)  # a real-time loop's period (short: the plans below are 50 ms)
    runner.close()
    return outs, adopted, pl.policy


def test_in_lockstep_a_plan_drives_from_the_next_step_however_long_it_took(slowplan, monkeypatch):
    monkeypatch.setattr(slowplan, "PLAN_S", 0.05)
    a, adopted_a, pol = _drive(_Jittered(1, seed=1), 40)
    b, adopted_b, _ = _drive(_Jittered(1, seed=2), 40)
    assert pol.adopted >= 3
    assert adopted_a == adopted_b  # every plan on the step after it was asked (asked every 10 steps from 0)
    assert [k for k, t in enumerate(adopted_a) if t] == [1, 11, 21, 31]
    assert all(not differing(x, y) for x, y in zip(a, b))  # the same to the bit


def test_a_real_time_runs_plans_replay_at_the_steps_it_took_them(slowplan, monkeypatch):
    monkeypatch.setattr(slowplan, "PLAN_S", 0.05)
    live, adopted, pol = _drive(_Jittered(None, seed=3), 40)
    assert pol.adopted >= 3
    took = [k for k, t in enumerate(adopted) if t]
    assert all(k >= asked + 3 for k, asked in zip(took, range(0, 40, 10))), took  # 50 ms of plan: 5 x 10 ms steps
    again, _, _ = _drive(ScriptedRunner(), 40, plans=adopted)
    assert all(not differing(x, y) for x, y in zip(live, again))


def test_a_control_step_never_waits_on_a_plan_in_flight():
    """The runner alone: a 1 s plan of pure Python while a 10 ms loop runs; no loop turn takes 20 ms."""
    r = ThreadRunner(None)
    got = []

    def spin():
        end = time.perf_counter() + 1.0
        while time.perf_counter() < end:
            sum(i * i for i in range(200))
        return "plan"

    worst, k = 0.0, 0
    r.begin(k, 0.0)
    r.submit("p", spin, got.append)
    t_end = time.perf_counter() + 1.5
    while time.perf_counter() < t_end:
        t0 = time.perf_counter()
        k += 1
        r.begin(k, k * 0.01)
        sum(i * i for i in range(2000))  # a control step's own work
        worst = max(worst, time.perf_counter() - t0)
        time.sleep(0.01)
    r.close()
    assert got == ["plan"] and r.stats()["ms_max"] >= 900
    assert worst < 0.02, worst
