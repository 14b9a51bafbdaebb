"""The onboard "network" of Bai's hybrid strategy: greedy action of the trained dueling DQN.

The decision layer (:mod:`stack.agents.decision`, section IV) calls it in the leader's
situation 2 and the followers' situations 2-3; PID drives in situation 1 (``hybrid = True``).
The network runs in numpy on the exported weights (``robot.drl.runtime: numpy``, the default:
:mod:`.numpy_net`, no torch imported) or in torch (``runtime: torch``, the ``drl`` extra;
``torch.set_num_threads(1)`` keeps one agent process on one core). Both take either weights file
(a ``.npz`` export or a torch state_dict); the weights are loaded once.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..base import Observation, Policy
from .config import DrlConfig
from .numpy_net import NumpyQNet, load_npz
from .observation import ACTIONS, goal_features, neighbour_features, scan_features

WEIGHTS = Path(__file__).with_name("weights") / "drl.pt"
"""The shipped weights, a torch state_dict (what training writes)."""
WEIGHTS_NPZ = WEIGHTS.with_suffix(".npz")
"""The same weights exported for numpy (``stack-train drl --export``; tests/test_lean.py checks they match)."""


def _state_dict(path: Path) -> dict:
    """The torch state_dict in ``path``: a torch file, or a ``.npz`` export."""
    import torch

    if path.suffix == ".npz":
        return {k: torch.from_numpy(v) for k, v in load_npz(path).items()}
    return torch.load(path, map_location="cpu", weights_only=True)


def load_network(path: str | Path | None = None):
    """The torch ``DuelingQNet`` with the weights at ``path`` (default: the shipped ones), in eval mode."""
    from .network import DuelingQNet

    net = DuelingQNet()
    net.load_state_dict(_state_dict(Path(path) if path else WEIGHTS))
    return net.eval()


def load_numpy_network(path: str | Path | None = None) -> NumpyQNet:
    """The numpy network with the weights at ``path`` (default: the shipped ``.npz``; a torch file needs torch)."""
    path = Path(path) if path else WEIGHTS_NPZ
    if path.suffix == ".npz":
        return NumpyQNet(load_npz(path))
    return NumpyQNet({k: v.numpy() for k, v in _state_dict(path).items()})


def features(obs: Observation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One observation -> the network's inputs (batch of one, numpy float32): scans, [o_g, o_v], o_r."""
    return (scan_features(obs.scans)[None], goal_features(obs.d_g, obs.alpha_g, obs.v, obs.w)[None],
            neighbour_features(obs.neighbours)[None])


def encode(obs: Observation):
    """:func:`features` as torch tensors."""
    import torch

    return tuple(torch.from_numpy(a) for a in features(obs))


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

    def __init__(self, weights: str | Path | None = None, *, net=None, threads: int = 1,
                 cfg: DrlConfig | None = None, radius: float = 0.5, fov: float = math.pi):
        self.cfg = cfg = cfg or DrlConfig(shield=False)
        # a torch module given, or runtime torch: torch; else numpy (a NumpyQNet, or any callable on numpy inputs)
        self.torch = hasattr(net, "eval") if net is not None else cfg.runtime == "torch"
        if self.torch:
            import torch

            if threads:
                torch.set_num_threads(threads)
            self.net = net.eval() if net is not None else load_network(weights or cfg.weights)
        else:
            self.net = net if net is not None else load_numpy_network(weights or cfg.weights)
        self.last_q: np.ndarray | None = None
        self.shield = (Shield(ACTIONS, radius=radius, fov=fov, horizon=cfg.shield_horizon, margin=cfg.shield_margin)
                       if cfg.shield else None)
        self.masked = 0  # steps at which the shield overruled the network's greedy action
        self.leader_hold = cfg.leader_hold
        self.centre_heading = cfg.centre_heading

    def q_values(self, obs: Observation) -> np.ndarray:
        if not self.torch:
            return self.net(*features(obs))[0]
        import torch

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
    geometry = {} if robot is None else {"radius": robot.radius, "fov": robot.lidar.fov}
    try:
        return DrlPolicy(weights, cfg=cfg, **geometry)
    except ModuleNotFoundError as e:  # runtime torch (or torch weights) where torch is not installed
        from .. import unavailable

        raise unavailable("drl", e) from None
