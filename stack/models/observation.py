"""What a robot sees of its target and its neighbours: the fields of the policies' ``Observation``.

One builder for the agent's decision layer (``stack/agents/decision.py``) and the training
worlds (``stack/train/fuzzyworld.py`` per robot, ``stack/train/drlworld.py`` vectorised), so
that what is trained is what is deployed (Bai 2022 section III-B; Chang 2020's MRC reads the
neighbours' reported states):

* a neighbour's position is its last report extrapolated along its reported velocity, at most
  :data:`PREDICT_HORIZON_S`; a report older than :data:`STALE_AFTER_S` is left out (the caller drops it);
* o_r: [distance, bearing] of the neighbours within comm range, farthest first (eq. 13, before
  normalisation), beside their reported states [x, y, yaw, v, w, age] and distances to their own goals;
* o_g: distance and bearing of the target (eq. 11-12, before normalisation).

The dataclass itself is :class:`stack.policies.base.Observation`; :func:`observation_fields`
returns its keyword arguments (this room imports nothing of ours).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .geometry import polar, polar_array

__all__ = ["PREDICT_HORIZON_S", "STALE_AFTER_S", "NeighbourView", "neighbour_polar_array", "neighbour_view",
           "observation_fields", "predicted"]

STALE_AFTER_S = 3.0  # [s] a neighbour not heard for this long is left out of the formation logic
PREDICT_HORIZON_S = 1.0  # [s] a report is extrapolated along its velocity at most this far

#: a neighbour's report: (x, y, yaw, v, w, age [s], d_goal or None)
Report = Sequence


def predicted(x: float, y: float, yaw: float, v: float, age: float,
              horizon: float = PREDICT_HORIZON_S) -> tuple[float, float]:
    """Position extrapolated along the reported velocity for ``age`` seconds, clipped to [0, horizon]."""
    age = max(0.0, min(horizon, age))
    return x + v * math.cos(yaw) * age, y + v * math.sin(yaw) * age


@dataclass(frozen=True)
class NeighbourView:
    """The neighbours as one robot sees them (see the module docstring)."""

    others: list[tuple[float, float]]
    """Predicted position of every neighbour given, in the order given."""
    dists: list[float]
    """Distance from the robot to each of ``others``."""
    polar: np.ndarray
    """(k, 2) [distance, bearing (robot frame)] of those within comm range, farthest first (o_r)."""
    states: np.ndarray
    """(k, 6) their reports [x, y, yaw, v, w, age >= 0], in the order given."""
    d_goals: np.ndarray
    """(k,) their reported distances to their own goals (NaN where not reported)."""

    @property
    def d_rmin(self) -> float:
        return min(self.dists, default=math.inf)

    @property
    def d_rmax(self) -> float:
        return max(self.dists, default=0.0)


def neighbour_view(me: tuple[float, float], yaw: float, reports: Sequence[Report], comm_range: float,
                   horizon: float = PREDICT_HORIZON_S) -> NeighbourView:
    """The view of the neighbours ``reports`` from a robot at ``me`` heading ``yaw``."""
    others = [predicted(r[0], r[1], r[2], r[3], r[5], horizon) for r in reports]
    pol = [polar(me, yaw, o) for o in others]
    keep = [k for k, p in enumerate(pol) if p[0] <= comm_range]
    nb = np.array(sorted((pol[k] for k in keep), reverse=True), dtype=float).reshape(-1, 2)
    states = np.array([(*reports[k][:5], max(0.0, reports[k][5])) for k in keep], dtype=float).reshape(-1, 6)
    d_goals = np.array([math.nan if reports[k][6] is None else reports[k][6] for k in keep], dtype=float)
    return NeighbourView(others, [p[0] for p in pol], nb, states, d_goals)


def observation_fields(x: float, y: float, yaw: float, v: float, w: float, target: tuple[float, float],
                       view: NeighbourView, *, scans: np.ndarray, scan_range: float, dt: float,
                       goal_velocity: tuple[float, float] = (0.0, 0.0), target_yaw: float | None = None,
                       alpha: float | None = None) -> dict:
    """Keyword arguments of ``Observation`` for a robot at (x, y, yaw) moving at (v, w), going to ``target``.

    ``alpha``: a bearing to aim at instead of the target's (Bai's follower situation 3, eq. 22)."""
    d_g, a_g = polar((x, y), yaw, target)
    return dict(d_g=d_g, alpha_g=a_g if alpha is None else alpha, v=v, w=w, neighbours=view.polar, scans=scans,
                goal_velocity=goal_velocity, yaw=yaw, scan_range=scan_range, dt=dt, target_yaw=target_yaw,
                x=x, y=y, target=(float(target[0]), float(target[1])), neighbour_states=view.states,
                neighbour_d_goal=view.d_goals)


def neighbour_polar_array(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, comm_range: float) -> tuple[np.ndarray, np.ndarray]:
    """o_r of every robot of every scene at once, from exact positions (age 0): x, y, yaw (..., R) ->
    ((..., R, R-1, 2) [distance, bearing] within comm range, farthest first, zero-padded; (..., R) their count).

    The vectorised form of :func:`neighbour_view`'s ``polar`` (the training worlds' radio is ideal)."""
    R = x.shape[-1]
    d, b = polar_array(x[..., :, None], y[..., :, None], yaw[..., :, None], x[..., None, :], y[..., None, :])
    key = np.where(np.eye(R, dtype=bool) | (d > comm_range), np.inf, -d)  # farthest first; self, out of range last
    order = np.argsort(key, axis=-1, kind="stable")[..., : R - 1]
    n = (np.take_along_axis(key, order, -1) < np.inf).sum(-1)
    out = np.stack([np.take_along_axis(d, order, -1), np.take_along_axis(b, order, -1)], -1)
    out[np.arange(R - 1) >= n[..., None]] = 0.0
    return out, n
