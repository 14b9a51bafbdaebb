"""The world's ground-truth log of a run (``truth.npz``) and every robot's target along it.

The world records one row per step (K steps, N robots in ``ids`` order); the report's
metrics are functions of this log. :func:`targets` adds, from the scenario, who leads at
each step and where each robot should be: the goal, or its slot (eq. (3)) around the
leader's true position, with the schedule and the failover rule the agents apply.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..scenario import Scenario


@dataclass(frozen=True)
class TruthLog:
    """Per-step ground truth as the world writes it to ``truth.npz``."""

    ids: list[int]
    """Robot ids, the column order of every (K, N) array."""
    t: np.ndarray
    """(K,) sim time of each step [s]."""
    x: np.ndarray
    """(K, N) true x [m]."""
    y: np.ndarray
    """(K, N) true y [m]."""
    alive: np.ndarray
    """(K, N) bool: the robot's agent was in the run at that step (not killed or crashed)."""
    v: np.ndarray
    """(K, N) true forward speed [m/s]."""
    yaw: np.ndarray | None = None
    """(K, N) true heading [rad], if logged."""
    w: np.ndarray | None = None
    """(K, N) true turn rate [rad/s], if logged."""

    @classmethod
    def load(cls, path: Path) -> "TruthLog":
        z = np.load(path)
        return cls(ids=[int(i) for i in z["ids"]], t=z["t"], x=z["x"], y=z["y"], alive=z["alive"], v=z["v"],
                   yaw=z["yaw"] if "yaw" in z else None, w=z["w"] if "w" in z else None)

    @classmethod
    def of(cls, ids: list[int], t, x, y, alive=None, v=None) -> "TruthLog":
        """A log from plain sequences (tests, tools): everyone alive and speed 0 unless given."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        return cls(ids=list(ids), t=np.asarray(t, float), x=x, y=y,
                   alive=np.ones(x.shape, bool) if alive is None else np.asarray(alive, bool),
                   v=np.zeros(x.shape) if v is None else np.asarray(v, float))

    @property
    def steps(self) -> int:
        return self.x.shape[0]

    def column(self, rid: int) -> int:
        return self.ids.index(rid)


@dataclass(frozen=True)
class Targets:
    """Where every robot should be at every step, from the scenario and the log."""

    leader: np.ndarray
    """(K,) the leading robot's id at each step, -1 without a formation or with nobody left."""
    tx: np.ndarray
    """(K, N) target x: the goal (leader, peers) or the slot; NaN for a robot gone from the formation."""
    ty: np.ndarray
    """(K, N) target y, as ``tx``."""
    following: np.ndarray
    """(K, N) bool: the robot was a follower with a slot (not leading, not gone, not frozen)."""
    connected: np.ndarray
    """(K,) bool: every follower with a slot within its comm range of the leader (True without a formation)."""

    def error(self, log: TruthLog) -> np.ndarray:
        """(K, N) distance from each robot to its target (NaN where it has none)."""
        return np.hypot(log.x - self.tx, log.y - self.ty)


def targets(sc: Scenario, log: TruthLog, frozen: np.ndarray) -> Targets:
    """Each robot's target at each step; ``frozen`` (K, N) marks agents that were frozen (not following)."""
    K, N = log.x.shape
    lead = np.full(K, -1)
    tx, ty = np.full((K, N), np.nan), np.full((K, N), np.nan)
    ok = np.ones(K, bool)
    f = sc.formation
    if f is None:
        for j, rid in enumerate(log.ids):
            tx[:, j], ty[:, j] = sc.robot(rid).goal
        return Targets(lead, tx, ty, np.zeros((K, N), bool), ok)
    idx = {rid: j for j, rid in enumerate(log.ids)}
    for k in range(K):
        dead = {log.ids[j] for j in np.nonzero(~log.alive[k])[0]}
        leader, slots = f.resolve(float(log.t[k]), dead)
        if leader is None:
            continue
        li = idx[leader]
        lead[k] = leader
        tx[k, li], ty[k, li] = f.goal
        for rid, sl in slots.items():  # eq. (3): the slot at (L, psi) from the leader
            j = idx[rid]
            tx[k, j] = log.x[k, li] + sl.L * math.cos(sl.psi)
            ty[k, j] = log.y[k, li] + sl.L * math.sin(sl.psi)
            ok[k] &= math.hypot(log.x[k, j] - log.x[k, li], log.y[k, j] - log.y[k, li]) <= sc.robot(rid).comm_range
    following = ~np.isnan(tx) & (lead[:, None] != np.array(log.ids)[None, :]) & ~frozen
    return Targets(lead, tx, ty, following, ok)
