"""The onboard "network" of Bai's hybrid strategy: greedy action of the trained dueling DQN.

The decision layer (:mod:`stack.agents.decision`, section IV) calls it in the leader's
situation 2 and the followers' situations 2-3; PID drives in situation 1 (``hybrid = True``).
Weights are a state_dict loaded once; ``torch.set_num_threads(1)`` keeps one agent process on
one core.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..base import Observation, Policy
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


class DrlPolicy(Policy):
    name = "drl"
    hybrid = True

    def __init__(self, weights: str | Path | None = None, *, net: DuelingQNet | None = None, threads: int = 1):
        if threads:
            torch.set_num_threads(threads)
        self.net = net.eval() if net is not None else load_network(weights)
        self.last_q: np.ndarray | None = None

    def q_values(self, obs: Observation) -> np.ndarray:
        with torch.inference_mode():
            return self.net(*encode(obs))[0].numpy()

    def act(self, obs: Observation) -> tuple[float, float]:
        self.last_q = q = self.q_values(obs)
        v, w = ACTIONS[int(np.argmax(q))]
        return float(v), float(w)


def make_drl(robot=None, *, seed: int = 0, weights: str | Path | None = None, **_) -> DrlPolicy:
    """Factory for the registry: the shipped weights unless ``weights`` names others (greedy: ``seed`` unused)."""
    return DrlPolicy(weights)
