"""The robot behaviour controller (RBC) of Chang 2020: lidar sectors, left/right boundary following
(eq. 15-16), target searching and the behaviour supervisor (Fig. 5, after Juang and Chang 2011).

Sectors (Fig. 2): the front half-plane, from the robot's right (0 deg) to its left (180 deg), is cut
into eight equal sectors L_1..L_8 (L_1 rightmost); each L_k is the shortest beam in it, clipped to
the lidar range. A wider or narrower lidar is cut over its own field of view.

Angles here are counter-clockwise positive (the stack's convention). The paper's theta_BF is
clockwise positive; the shipped consequents are stored in our convention (a left BF controller
that sees the wall too close returns a negative angle: turn right, away from it).

**Eq. (16) as we read it.** The right controller shares the left one's antecedents with the sensors
mirrored about the heading: B_i1..B_i4 act on (L_4, L_3, L_2, L_1) where the left one's act on
(L_5, L_6, L_7, L_8), and the consequent is negated. (The printed "L_1 is B_i1 ... L_4 is B_i4"
pairs L_5, the sector next to the heading, with L_1, the sector at the robot's right side; that is
not a mirror image, and the paper says the right behaviour is the mirror of the left.) So the
right controller on a mirrored scan returns exactly the negated angle (tested).

**The supervisor (Fig. 5) as we read it.** TS -> BF when an obstacle is within ``d_detect`` in the
front sectors L_2..L_7 and the search direction is not free, or within ``d_near`` whatever the
search direction (BF side: left if min(L_5..L_8) <= min(L_1..L_4), so two robots meeting head on
both turn right); d_1 (distance to the target) is recorded and c_step set to 0. In BF, c_step
counts up; the robot may leave BF only where the search direction is free (the target in front,
the sector it lies in and both neighbours farther than min(d_goal, d_detect)). There d_2 is
measured. The printed rule, "if d_1 > d_2, or if c_step > 100, the robot keeps the original BF
behavior; otherwise [it] switches from BF to TS", would leave BF only when the robot has made no
progress and within 100 steps, the opposite of the classic rule of Juang and Chang (2011) that
it cites (leave the boundary once closer to the target than where it was met, which prevents
dead cycles). We read it as: keep BF while d_2 >= d_1 and c_step <= ``c_min`` (100); switch to
TS when d_2 < d_1 or c_step > ``c_min``. The counter bounds how long a robot follows a boundary
without progress (e.g. another robot, which moves with it). Two additions: no obstacle within the
lidar range at all -> TS (the paper's first sentence on the supervisor); within ``d_release`` of
the target a free search direction ends BF at once (robots arriving together are obstacles to
each other and must not lead each other away).

Steering angle -> yaw rate: w = theta / ``turn_time`` (the driver clamps to w_max).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..checks import check_numbers
from .tsk import TSK

N_SECTORS = 8
LEFT = (4, 5, 6, 7)  # L5..L8 (0-based)
RIGHT_MIRROR = (3, 2, 1, 0)  # L4..L1: the mirror images of L5..L8, eq. (16) as read above


def sector_edges(fov: float) -> np.ndarray:
    """The 9 edges of the sectors [rad, robot frame, -fov/2 .. +fov/2], right to left."""
    return np.linspace(-fov / 2, fov / 2, N_SECTORS + 1)


def sectors(scan: np.ndarray, fov: float, range_max: float) -> np.ndarray:
    """L_1..L_8 from one scan whose beams are spaced evenly from -fov/2 to +fov/2 (both ends included)."""
    scan = np.asarray(scan, float)
    if scan.size == 0:
        return np.full(N_SECTORS, range_max)
    r = np.where(np.isfinite(scan), np.minimum(scan, range_max), range_max)
    if scan.size == 1:
        return np.full(N_SECTORS, float(r[0]))
    idx = np.minimum((np.arange(scan.size) * N_SECTORS) // scan.size, N_SECTORS - 1)  # beam -> sector
    out = np.full(N_SECTORS, range_max)
    np.minimum.at(out, idx, r)
    return out


def sector_of(angle: float, fov: float) -> int | None:
    """Which sector (0-based) looks along ``angle`` [rad, robot frame]; None outside the field of view."""
    if abs(angle) > fov / 2:
        return None
    return min(int((angle + fov / 2) / (fov / N_SECTORS)), N_SECTORS - 1)


class BoundaryFollower:
    """Left and right BF controllers from one left TSK (4 inputs, 1 output), eq. (15)-(16)."""

    def __init__(self, left: TSK):
        if left.m.shape[1] != 4 or left.a.shape[1] != 1:
            raise ValueError("the BF controller has 4 inputs (L5..L8) and 1 output")
        self.left_tsk = left

    def left(self, L: np.ndarray) -> float:
        """Eq. (15): theta_BF from L5..L8."""
        return float(self.left_tsk(np.asarray(L)[list(LEFT)])[0])

    def right(self, L: np.ndarray) -> float:
        """Eq. (16): the same antecedents on the mirrored sensors, negated consequents."""
        return -float(self.left_tsk(np.asarray(L)[list(RIGHT_MIRROR)])[0])


TS, BF_LEFT, BF_RIGHT = "TS", "BF-left", "BF-right"


@dataclass
class SupervisorConfig:
    d_detect: float = 1.2
    """[m] an obstacle this near in the front sectors L2..L7 starts boundary following."""
    d_near: float = 0.7
    """[m] an obstacle this near in L2..L7 starts boundary following even when the search direction is free."""
    c_min: int = 100
    """Fig. 5's step counter: after this many BF steps a free search direction ends BF even without progress."""
    d_release: float = 3.0
    """[m] this near the target a free search direction ends BF at once."""

    def __post_init__(self):
        check_numbers(self)


class BehaviourSupervisor:
    """Fig. 5: target searching vs left/right boundary following, with d_1, d_2 and c_step."""

    def __init__(self, cfg: SupervisorConfig | None = None, *, fov: float = math.pi, range_max: float = 5.0):
        self.cfg = cfg or SupervisorConfig()
        self.fov = fov
        self.range_max = range_max
        self.reset()

    def reset(self) -> None:
        self.behaviour = TS
        self.d1 = math.inf
        self.c_step = 0

    def target_free(self, L: np.ndarray, d_goal: float, theta_goal: float) -> bool:
        """The target lies in front and the sectors around its direction are farther than min(d_goal, d_detect)."""
        k = sector_of(theta_goal, self.fov)
        if k is None:
            return False
        near = L[max(0, k - 1): k + 2]
        return bool(near.min() > min(d_goal, self.cfg.d_detect))

    def step(self, L: np.ndarray, d_goal: float, theta_goal: float) -> str:
        """The behaviour for this control step (call once per step)."""
        L = np.asarray(L, float)
        if (L >= self.range_max - 1e-6).all():  # nothing within the sensing range: straight to the target
            self.behaviour, self.c_step = TS, 0
            return TS
        if self.behaviour == TS:
            front = L[1:7].min()
            if front < self.cfg.d_near or (front < self.cfg.d_detect and not self.target_free(L, d_goal, theta_goal)):
                self.behaviour = BF_LEFT if L[4:].min() <= L[:4].min() else BF_RIGHT
                self.d1, self.c_step = d_goal, 0  # Fig. 5: record d_1, reset the counter
            return self.behaviour
        self.c_step += 1
        if self.target_free(L, d_goal, theta_goal):
            d2 = d_goal
            if d2 < self.d1 or self.c_step > self.cfg.c_min or d2 < self.cfg.d_release:
                self.behaviour, self.c_step = TS, 0
        return self.behaviour


@dataclass
class RbcConfig:
    turn_time: float = 1.0
    """[s] steering angle -> yaw rate: w = theta / turn_time."""
    supervisor: SupervisorConfig = None  # type: ignore[assignment]

    def __post_init__(self):
        if self.supervisor is None:
            self.supervisor = SupervisorConfig()


class RobotBehaviourController:
    """Sectors -> supervisor -> BF (left/right TSK) or TS -> steering angle theta_r."""

    def __init__(self, bf: BoundaryFollower, cfg: RbcConfig | None = None, *, fov: float = math.pi,
                 range_max: float = 5.0):
        self.cfg = cfg or RbcConfig()
        self.bf = bf
        self.fov = fov
        self.range_max = range_max
        self.supervisor = BehaviourSupervisor(self.cfg.supervisor, fov=fov, range_max=range_max)

    def reset(self) -> None:
        self.supervisor.reset()

    def steer(self, L: np.ndarray, d_goal: float, theta_goal: float, theta_adj: float) -> tuple[str, float]:
        """(behaviour, steering angle theta_r [rad, CCW]); TS steers to theta_adj (eq. 7's output)."""
        b = self.supervisor.step(L, d_goal, theta_adj)  # "free" is judged along the search direction
        if b == BF_LEFT:
            return b, self.bf.left(L)
        if b == BF_RIGHT:
            return b, self.bf.right(L)
        return b, float(theta_adj)
