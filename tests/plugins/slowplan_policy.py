"""A test double: a policy whose planner is slow on purpose (``POLICIES`` for ``FORMATION_STACK_PLUGINS``).

Every ``ASK_EVERY_S`` it asks ``self.planner`` for a plan that computes for ``PLAN_S`` seconds of pure Python
(holding the GIL as a real Python planner does, harsher than a sleep) and hands back the straight way to the
goal. It drives the last plan it adopted at half speed; before its first plan it stands still (the safe
fallback). If the plan ran inside the control step, every such step would take 2 s.
"""

from __future__ import annotations

import math
import time

from stack.plugins import Plugin
from stack.policies.base import Observation, Policy

PLAN_S = 2.0
ASK_EVERY_S = 1.0


def _slow_plan(target: tuple[float, float]) -> tuple[float, float]:
    end = time.perf_counter() + PLAN_S
    n = 0
    while time.perf_counter() < end:  # pure Python: the GIL held but for the interpreter's switches
        n += sum(i * i for i in range(200))
    return target


class SlowPlanPolicy(Policy):
    name = "slowplan"
    hybrid = False

    def __init__(self) -> None:
        self.k = 0
        self.asked_k: int | None = None
        self.plan: tuple[float, float] | None = None
        self.adopted = 0

    def _adopt(self, target: tuple[float, float]) -> None:
        self.plan = target
        self.adopted += 1

    def act(self, obs: Observation) -> tuple[float, float]:
        self.k += 1
        target = obs.target or (obs.x + obs.d_g * math.cos(obs.yaw + obs.alpha_g),
                                obs.y + obs.d_g * math.sin(obs.yaw + obs.alpha_g))
        every = max(1, round(ASK_EVERY_S / obs.dt))
        if (self.asked_k is None or self.k - self.asked_k >= every) and not self.planner.busy("slow"):
            self.asked_k = self.k
            goal = (float(target[0]), float(target[1]))
            self.planner.submit("slow", lambda: _slow_plan(goal), self._adopt)
        if self.plan is None or obs.d_g < 0.2:
            return 0.0, 0.0
        err = math.atan2(self.plan[1] - obs.y, self.plan[0] - obs.x) - obs.yaw
        err = math.atan2(math.sin(err), math.cos(err))
        return 0.5 * max(0.0, math.cos(err)), 1.5 * err


def make_slowplan(robot, **_) -> SlowPlanPolicy:
    return SlowPlanPolicy()


POLICIES = [Plugin("slowplan", None, "slowplan_policy:make_slowplan", summary="test double: a 2 s planner")]
