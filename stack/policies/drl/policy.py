"""The onboard "network" of Bai's hybrid strategy: greedy action of the trained dueling DQN.

The decision layer (:mod:`stack.agents.decision`, section IV) calls it in the leader's
situation 2 and the followers' situations 2-3; PID drives in situation 1 (``hybrid = True``).
Weights are a state_dict loaded once; ``torch.set_num_threads(1)`` keeps one agent process on
one core.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..base import Observation, Policy
from .config import DrlConfig
from .network import DuelingQNet
from .observation import ACTIONS, goal_features, neighbour_features, scan_features

WEIGHTS = Path(__file__).with_name("weights") / "drl.pt"


def load_network(path: str | Path | None = None) -> DuelingQNet:
    """The network with the weights at ``path`` (default: the shipped ones), in eval mode."""
    net = DuelingQNet()
    net.load_state_dict(torch.load(Path(path) if path else WEIGHTS, map_location="cpu", weights_only=True))
    return net.eval()


def encode(obs: Observation) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One observation -> the network's inputs (batch of one): scans, [o_g, o_v], o_r."""
    z = torch.from_numpy(scan_features(obs.scans))[None]
    g = torch.from_numpy(goal_features(obs.d_g, obs.alpha_g, obs.v, obs.w))[None]
    nb = torch.from_numpy(neighbour_features(obs.neighbours))[None]
    return z, g, nb


class Shield:
    """Masks actions that would hit what the newest scan sees (a shield in the sense of Alshiekh et al. 2018).

    Each action (v, w) is followed along its arc for ``horizon`` (at ``steps`` points); it is unsafe when any
    point comes within ``radius + margin`` of a scan return (the returns in the robot's frame; a return at the
    range limit is no return), unless the robot is that near already and the arc gets it no nearer (so it can
    back out of where it is). Standing and turning on the spot are always allowed. Beams cover -fov/2..fov/2,
    both ends included (the contract's lidar)."""

    def __init__(self, actions: np.ndarray, *, radius: float, fov: float, horizon: float, margin: float, steps: int = 6):
        t = np.linspace(horizon / steps, horizon, steps)  # (S,)
        v, w = actions[:, 0:1], actions[:, 1:2]  # (A, 1)
        th = w * t
        small = np.abs(w) < 1e-9
        ws = np.where(small, 1.0, w)
        self.px = np.where(small, v * t, v / ws * np.sin(th))  # (A, S) arc points, robot frame
        self.py = np.where(small, 0.0, v / ws * (1.0 - np.cos(th)))
        self.moving = np.abs(actions[:, 0]) > 0  # a round robot turning on the spot moves nothing
        self.clear = radius + margin
        self.slack = 0.005  # [m] "no nearer": within this of the distance now (sampled beams and arcs)
        self.fov = fov
        self._angles: dict[int, np.ndarray] = {}

    def safe(self, scan: np.ndarray, range_max: float) -> np.ndarray:
        """(A,) bool: which actions keep clear of the returns in ``scan`` (metres)."""
        scan = np.asarray(scan, float).ravel()
        n = scan.size
        if n == 0:
            return np.ones(self.px.shape[0], bool)
        ang = self._angles.get(n)
        if ang is None:
            ang = self._angles[n] = np.linspace(-self.fov / 2, self.fov / 2, n)
        hit = scan < range_max - 1e-6
        if not hit.any():
            return np.ones(self.px.shape[0], bool)
        ox, oy = scan[hit] * np.cos(ang[hit]), scan[hit] * np.sin(ang[hit])  # (H,)
        d2 = (self.px[..., None] - ox) ** 2 + (self.py[..., None] - oy) ** 2  # (A, S, H)
        arc = np.sqrt(d2.min(axis=(1, 2)))
        now = float(np.sqrt((ox ** 2 + oy ** 2).min()))
        ok = (arc > self.clear) | (arc >= now - self.slack)  # keeps clear, or (already too near) gets no nearer
        return ok | ~self.moving  # standing or turning on the spot is always allowed


class DrlPolicy(Policy):
    name = "drl"
    hybrid = True

    def __init__(self, weights: str | Path | None = None, *, net: DuelingQNet | None = None, threads: int = 1,
                 cfg: DrlConfig | None = None, radius: float = 0.5, fov: float = math.pi):
        if threads:
            torch.set_num_threads(threads)
        self.cfg = cfg = cfg or DrlConfig(shield=False)
        self.net = net.eval() if net is not None else load_network(weights or cfg.weights)
        self.last_q: np.ndarray | None = None
        self.shield = (Shield(ACTIONS, radius=radius, fov=fov, horizon=cfg.shield_horizon, margin=cfg.shield_margin)
                       if cfg.shield else None)
        self.masked = 0  # steps at which the shield overruled the network's greedy action
        self.leader_hold = cfg.leader_hold

    def q_values(self, obs: Observation) -> np.ndarray:
        with torch.inference_mode():
            return self.net(*encode(obs))[0].numpy()

    def act(self, obs: Observation) -> tuple[float, float]:
        self.last_q = q = self.q_values(obs)
        a = int(np.argmax(q))
        if self.shield is not None and np.asarray(obs.scans).size:
            ok = self.shield.safe(np.asarray(obs.scans)[-1], obs.scan_range or 5.0)
            if not ok[a]:
                self.masked += 1
                a = int(np.argmax(np.where(ok, q, -np.inf)))
        v, w = ACTIONS[a]
        return float(v), float(w)


def make_drl(robot=None, *, seed: int = 0, weights: str | Path | None = None, **_) -> DrlPolicy:
    """Factory for the registry: ``robot.drl`` (:class:`DrlConfig`; the shield on by default), the shipped
    weights unless ``weights`` or ``robot.drl.weights`` names others (greedy: ``seed`` unused)."""
    cfg = robot.config_for("drl") if robot is not None else DrlConfig()
    if robot is None:
        return DrlPolicy(weights, cfg=cfg)
    return DrlPolicy(weights, cfg=cfg, radius=robot.radius, fov=robot.lidar.fov)
