"""PID go-to-goal: drive straight toward the target (Bai 2022, situation 1 of both roles).

Heading: w = k_w e + k_i sum(e) dt + k_d de/dt on the bearing error e = alpha_g.
Speed:   v = (k_v d_g + u_ff) cos(e), floored at 0 (no reversing), capped at v_cap,
where u_ff is the target's own speed along the line of sight (a follower's slot moves
with the leader; zero for a fixed goal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..estimation.pose import wrap as _wrap
from ..settings import check, rule
from .base import Observation, Policy


@dataclass(frozen=True)
class PidConfig:
    """``robot.pid``: gains of the go-to-goal PID policy (every other ``hybrid`` policy's situation 1 too)."""

    RULE = (">= 0",)

    k_v: float = 0.8
    """Linear speed per metre of distance to the target [1/s]."""
    k_w: float = 2.0
    """Angular rate per radian of heading error [1/s]."""
    k_i: float = 0.0
    """Integral gain on the heading error."""
    k_d: float = 0.1
    """Derivative gain on the heading error."""
    v_cruise: float = field(default=0.6, metadata=rule(">= 0", "<= 1"))
    """The leader's cruise speed, a fraction of ``v_max`` (a follower's cap is ``v_max``)."""
    arrive: float = 0.05
    """[m] within this of a fixed target the robot holds still."""

    def __post_init__(self):
        check(self)


class PidPolicy(Policy):
    name = "pid"
    needs_lidar = False  # go-to-goal: drives on the estimate alone

    def __init__(self, cfg: PidConfig | None = None, v_cap: float = 1.0):
        self.g = cfg or PidConfig()
        self.v_cap = v_cap  # the speed this policy asks for at most [m/s]
        self._int = 0.0
        self._prev: float | None = None

    def reset(self) -> None:
        self._int, self._prev = 0.0, None

    def act(self, obs: Observation) -> tuple[float, float]:
        g = self.g
        # the goal's velocity in the robot frame, and its part along the line of sight
        gvx, gvy = obs.goal_velocity
        c, s = math.cos(obs.yaw), math.sin(obs.yaw)
        fx, fy = c * gvx + s * gvy, -s * gvx + c * gvy
        u_ff = fx * math.cos(obs.alpha_g) + fy * math.sin(obs.alpha_g)
        if obs.d_g < g.arrive and math.hypot(gvx, gvy) < 1e-3:
            self.reset()
            return 0.0, 0.0
        # aim at the goal; when it moves and we are close, aim along its motion instead
        e = obs.alpha_g
        if obs.d_g < 0.3 and math.hypot(gvx, gvy) > 1e-3:
            e = math.atan2(fy, fx)
        de = 0.0 if self._prev is None else _wrap(e - self._prev) / obs.dt
        self._prev = e
        self._int = max(-1.0, min(1.0, self._int + e * obs.dt))
        w = g.k_w * e + g.k_i * self._int + g.k_d * de
        v = (g.k_v * obs.d_g + max(0.0, u_ff)) * math.cos(e)
        v = max(0.0, min(self.v_cap, v))
        return v, w


def make_pid(robot, **_) -> PidPolicy:
    """Factory: ``robot.pid`` (:class:`PidConfig`); the leader cruises at ``v_cruise * v_max``."""
    cfg = robot.config_for("pid")
    return PidPolicy(cfg, v_cap=robot.v_max * (cfg.v_cruise if robot.role == "leader" else 1.0))
