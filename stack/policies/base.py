"""The policy interface: ``act(observation) -> (v, w)``.

A policy sees an ``Observation`` in the robot's own frame and returns body-frame
velocities; it imports no Zenoh, no driver and no world, so it can be trained and tested
alone. Limits are enforced by the driver base, not here.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Observation:
    """What one robot knows at one control step (Bai 2022 section III-B, before normalisation).

    d_g, alpha_g: distance [m] and bearing [rad, robot frame] of the target, eq. (11)-(12).
    v, w: the robot's current velocity, o_v.
    neighbours: (n, 2) array of [distance, bearing] of robots within comm range, o_r,
        in reverse order of distance (farthest first).
    scans: (k, beams) array, the last k lidar scans [m], newest last, o_z.
    goal_velocity: world-frame velocity of the target (a follower's slot moves with the leader).
    yaw: the robot's heading [rad] (to turn goal_velocity into the robot frame).
    target_yaw: the leader's heading [rad, world frame] when the target is a follower's slot.
    scan_range: the lidar's maximum range [m].
    """

    d_g: float
    alpha_g: float
    v: float
    w: float
    neighbours: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    scans: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    goal_velocity: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0
    scan_range: float = 5.0
    dt: float = 0.1
    target_yaw: float | None = None  # heading of what the target follows (a follower's leader); None for a fixed goal
    x: float = 0.0  # the robot's own estimated position [m, world frame] (planners that keep a map need it)
    y: float = 0.0
    target: tuple[float, float] | None = None  # the target [m, world frame]: the goal, or a follower's slot
    neighbour_states: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    """(n, 6) rows [x, y, yaw, v, w, age]: the states the robots in comm range last broadcast (world frame;
    age [s] since they were stamped), for policies that coordinate on them (Chang 2020's MRC)."""
    neighbour_d_goal: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(n,) beside ``neighbour_states``: each one's distance to its own goal as it reported it [m] (arrival-time
    peers; NaN where the sender did not say)."""


class Policy(ABC):
    """A formation policy: one ``Observation`` in, one body-frame command ``(v, w)`` out, every control step.

    A policy is one module and one registry line (``stack.plugins``); its settings are a typed config under
    ``robot.<name>`` in the scenario. The step pipeline (``stack.agents.step``) builds the observation, runs
    the guard over the command and applies the speed limits, so a policy only decides.
    """

    name = "base"
    hybrid = True
    """True: the policy is the "network" of Bai's hybrid strategy (PID drives in situation 1);
    False: the policy drives in every situation (its paper has its own avoidance)."""
    centre_heading = True
    """Hybrid followers in situation 3 (an obstacle within d_safe) aim at the centre of the robots ahead (Bai's
    eq. 21-22) instead of their slot; False: at the slot, as in the other situations."""
    needs_lidar = True
    """False: the policy drives without the lidar (``pid``: go-to-goal only), so a stale scan does not stop it."""
    leader_hold: tuple[float, float] | None = None
    """Hybrid leaders: (start, stop) fractions of d_com over which the leader's speed falls to zero as its
    farthest robot gets farther (ours, beyond eq. 20; see ``DecisionLayer.leader_speed``); None: eq. (20) only."""

    @property
    def planner(self):
        """Where this policy's slow work runs (``stack.planning.runner``): a policy alone plans inline; the step
        pipeline hands it a runner that keeps planning out of the control step (``StepPipeline.use_planner``)."""
        r = self.__dict__.get("_planner")
        if r is None:
            from ..planning.runner import PlanRunner

            r = self._planner = PlanRunner()
        return r

    @planner.setter
    def planner(self, runner) -> None:
        self._planner = runner

    @abstractmethod
    def act(self, obs: Observation) -> tuple[float, float]:
        """Body-frame (v, w) for this step."""

    def reset(self) -> None:
        """Forget internal state (integrators, recurrent memory)."""
