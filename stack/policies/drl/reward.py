"""Bai 2022 eq. (14)-(17): r_t = r_g + r_c + r_a, vectorised over robots (numpy).

  eq. (15) r_g = 20                                   if |p_t - p_g| <= 0.5
               = 0.5 (|p_{t-1} - p_g| - |p_t - p_g|)  otherwise
  eq. (16) r_c = -1.0  if |p_t - p~_t| < 2 R_d or |p_t - B_k| < R_d     (a collision)
               = -0.3  else if |p_t - p~_t| < 3 R_d or |p_t - B_k| < 2 R_d
               = 0     otherwise
  eq. (17) r_a = -0.05 (|v_t - v_{t-1}| + |w_t - w_{t-1}|)   (commanded actions)
  ours     a robot arrives only where ``can_arrive`` (a follower whose slot still moves with its leader
           earns eq. (15)'s progress term, not its arrival: stage 3's ``follow`` scenes)
  ours     r_c's collision value is -collision_penalty (default 1.0, eq. 16's; ``stack-train drl
           --collision-penalty``: a follower whose slot moves on has little future reward to lose by colliding)
  ours     r_t -= time_penalty on every step that does not arrive (default 0: the paper's reward;
           ``stack-train drl --time-penalty`` sets it, see the README: without it, standing still
           is worth 0 and the greedy policy learnt to stand still in 18 % of held-out scenes)

|p_t - p~_t| is the centre distance to the nearest other robot, |p_t - B_k| the distance from
the robot's centre to the nearest obstacle surface.
"""

from __future__ import annotations

import numpy as np

R_D = 0.5  # Table II
GOAL_TOL = 0.5  # eq. (15)
R_GOAL = 20.0
K_PROGRESS = 0.5
R_COLLIDE = -1.0
R_NEAR = -0.3
K_ACTION = 0.05


def reward(d_prev, d_now, d_robot, d_obstacle, a_prev, a_now, radius: float = R_D, time_penalty: float = 0.0,
           can_arrive=True, collision_penalty: float = -R_COLLIDE):
    """Returns (r, arrived, collided), arrays of the broadcast shape of the inputs.

    d_prev, d_now: distance to the target before and after the step; d_robot: centre distance to
    the nearest other robot (inf: none); d_obstacle: distance to the nearest obstacle surface;
    a_prev, a_now: (..., 2) commanded [v, w] of the previous and this step; can_arrive: where reaching the
    target counts as arriving (False: the target moves on, only the progress term)."""
    d_prev, d_now = np.asarray(d_prev, float), np.asarray(d_now, float)
    d_robot, d_obstacle = np.asarray(d_robot, float), np.asarray(d_obstacle, float)
    arrived = (d_now <= GOAL_TOL) & np.asarray(can_arrive, bool)
    r_g = np.where(arrived, R_GOAL, K_PROGRESS * (d_prev - d_now))  # eq. (15)
    collided = (d_robot < 2 * radius) | (d_obstacle < radius)
    near = (d_robot < 3 * radius) | (d_obstacle < 2 * radius)
    r_c = np.where(collided, -collision_penalty, np.where(near, R_NEAR, 0.0))  # eq. (16)
    da = np.abs(np.asarray(a_now, float) - np.asarray(a_prev, float))
    r_a = -K_ACTION * (da[..., 0] + da[..., 1])  # eq. (17)
    r_t = np.where(arrived, 0.0, -time_penalty)  # ours (0: eq. 14 exactly)
    return r_g + r_c + r_a + r_t, arrived, collided  # eq. (14)
