"""The multiple robot coordinator (MRC) of Chang 2020, computed by every robot for itself.

Inputs (section "The proposed models"), robots ranked by ascending distance to the target:
  x = (D_goal^rank1, D_goal^rankn, v_r^rank1, v_r^rankn, Delta D),  Delta D = D^rankn - D^rank1
normalised here by ``d_scale`` (distances) and ``v_scale`` (speeds) before either coordinator.

  eq. (1)  alpha_i = (i - 1) / (n - 1) (alpha_n - alpha_1) + alpha_1,  alpha_i in [0.5, 1.5]
  eq. (2)  v_r^i(t) = alpha_i v_r^i(t - 1)                              (bounded: no robot stops)
  eq. (7)  theta_adj^i = theta_goal^i + beta_i theta_max_adj,           theta_max_adj = 90 deg
  eq. (8)  beta_i = sqrt((1 / alpha_i) (1 - D_goal^i / D_goal^rankn))
  FLC_SR   a zero-order TSK (eq. 3-6) with 5 inputs and the 2 outputs (alpha_1, alpha_n)
  LSTM     two peephole LSTM blocks, eq. (9)-(14), y in (-1, 1)^2 -> alpha = 1 + 0.5 y in (0.5, 1.5)

**Decentralised.** The paper's MRC is one central controller. Here every agent runs the same
coordinator on what it knows: its own distance and speed, and those of the robots it has heard
from (:class:`PeerEstimate`). It ranks them all, evaluates FLC_SR (or the LSTM) for (alpha_1,
alpha_n), takes its own alpha_i by eq. (1) at its own rank, and updates only its own speed by
eq. (2) and its own heading by eq. (7)-(8). With the same information every agent computes the
same alphas the central MRC would; no process is a single point of failure, and a robot that
hears nobody drives alone (alpha = 1). A peer's state may be old (packet loss): its distance is
extrapolated by its speed over its age and its weight in the ranking kept; a peer older than
``max_age`` is left out.

**Heading adjustment.** Algorithm 1 prints "(Delta D > 0.1 m or D^rankn > 10 m)"; the text says
the adjustment goes on "until either Delta D < 0.1 m or each robot is within 10 m of the target".
We follow the text: eq. (7)-(8) apply while Delta D >= 0.1 m and D^rankn > 10 m, and only in
target searching. The sign of beta's turn (left) is the paper's eq. (7) as printed.

**Terminal matching (ours).** Eq. (2) is a multiplicative integrator on normalised inputs: with every
robot at the speed bound and a gap of under a metre (1/50 of the inputs' scale) nothing slows the
nearer robots. Inside ``d_near_all``, where the paper stops the heading adjustment because the robots
are close, a robot of rank < n drives at most v_n D_goal^i / D_goal^rankn (the farthest robot's
time to go); ``terminal_match = False`` leaves eq. (2) alone.

**Ordering.** The coordinator's purpose is to slow the nearest robot relative to the farthest; we
take (alpha_1, alpha_n) = (min, max) of the two outputs, so the farthest robot's factor is never
the smaller one (with eq. (1), alpha is non-decreasing in rank).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..checks import check_numbers
from .tsk import TSK

ALPHA_MIN, ALPHA_MAX = 0.5, 1.5


def interpolate_alphas(alpha_1: float, alpha_n: float, n: int) -> np.ndarray:
    """Eq. (1): the speed factors of ranks 1..n (ranks 1 and n are FLC_SR's own outputs)."""
    if n == 1:
        return np.array([alpha_1])
    i = np.arange(1, n + 1)
    return np.clip((i - 1) / (n - 1) * (alpha_n - alpha_1) + alpha_1, ALPHA_MIN, ALPHA_MAX)


def beta(alpha_i: float, d_i: float, d_n: float) -> float:
    """Eq. (8); 0 for the farthest robot."""
    if d_n <= 0:
        return 0.0
    return math.sqrt(max(0.0, 1.0 - d_i / d_n) / max(alpha_i, 1e-6))


@dataclass
class PeerEstimate:
    """What a robot knows of another: distance to the target [m], speed [m/s], age of that knowledge [s]."""

    d_goal: float
    v: float
    age: float = 0.0


@dataclass
class MrcConfig:
    d_scale: float = 50.0
    """[m] distances are divided by this before FLC_SR / the LSTM (the paper's fields are under 50 m)."""
    v_scale: float = 1.0
    """[m/s] speeds are divided by this."""
    v_min: float = 0.2
    """[m/s] lower speed bound of eq. (2) (robots are not allowed to stop)."""
    v_max: float = 0.8
    """[m/s] upper speed bound of eq. (2)."""
    v0: float = 0.5
    """[m/s] initial speed (Algorithm 1: 0.5 m/s); also the constant speed without an MRC."""
    theta_max_adj: float = math.pi / 2
    """Eq. (7): theta_max_adj (90 deg)."""
    delta_d_stop: float = 0.1
    """[m] the heading adjustment stops when Delta D is below this ..."""
    d_near_all: float = 10.0
    """[m] ... or when every robot is within this of the target."""
    max_age: float = 3.0
    """[s] peers whose knowledge is older than this are left out."""
    terminal_match: bool = True
    """Ours: once every robot is within ``d_near_all`` (where eq. 7-8 stop), a robot nearer than the farthest
    drives at most v_n D_goal^i / D_goal^rankn, so that it arrives when the farthest does (False: eq. 2 alone)."""

    def __post_init__(self):
        check_numbers(self, positive=("d_scale", "v_scale"))


class FlcSr:
    """FLC_SR: 5 inputs -> (alpha_1, alpha_n), zero-order TSK (eq. 3-6)."""

    def __init__(self, tsk: TSK):
        if tsk.m.shape[1] != 5 or tsk.a.shape[1] != 2:
            raise ValueError("FLC_SR has 5 inputs and 2 outputs")
        self.tsk = tsk

    def reset(self) -> None:
        pass

    def __call__(self, x: np.ndarray) -> tuple[float, float]:
        a1, an = np.clip(self.tsk(x), ALPHA_MIN, ALPHA_MAX)
        return float(a1), float(an)


def _sigmoid(z):
    return 1.0 / (1.0 + np.exp(-z))


@dataclass
class LstmWeights:
    """Two peephole LSTM blocks (Greff 2017 "vanilla"), 5 inputs: W (4, 2, 5), R (4, 2, 2), p (3, 2), b (4, 2).

    Gate order z, i, f, o for W, R, b; i, f, o for p. Biases are fixed at 0.5 ("during the training
    process, all bias weights are set to 0.5") and not part of a particle."""

    W: np.ndarray
    R: np.ndarray
    p: np.ndarray
    b: np.ndarray = field(default_factory=lambda: np.full((4, 2), 0.5))

    N_PARAMS = 4 * 2 * 5 + 4 * 2 * 2 + 3 * 2

    @classmethod
    def from_vector(cls, vec) -> "LstmWeights":
        vec = np.asarray(vec, float)
        if vec.size != cls.N_PARAMS:
            raise ValueError(f"expected {cls.N_PARAMS} LSTM parameters, got {vec.size}")
        return cls(vec[:40].reshape(4, 2, 5), vec[40:56].reshape(4, 2, 2), vec[56:62].reshape(3, 2))

    def to_vector(self) -> np.ndarray:
        return np.concatenate([self.W.ravel(), self.R.ravel(), self.p.ravel()])

    def to_dict(self) -> dict:
        return {"W": self.W.tolist(), "R": self.R.tolist(), "p": self.p.tolist(), "b": self.b.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "LstmWeights":
        return cls(np.array(d["W"]), np.array(d["R"]), np.array(d["p"]), np.array(d.get("b", np.full((4, 2), 0.5))))


class LstmMrc:
    """The recurrent MRC: eq. (9)-(14) once per control step; same interface as :class:`FlcSr`."""

    def __init__(self, w: LstmWeights):
        self.w = w
        self.reset()

    def reset(self) -> None:
        self.y = np.zeros(2)
        self.c = np.zeros(2)

    def __call__(self, x: np.ndarray) -> tuple[float, float]:
        W, R, p, b = self.w.W, self.w.R, self.w.p, self.w.b
        z = np.tanh(W[0] @ x + R[0] @ self.y + b[0])  # eq. (9) block input
        i = _sigmoid(W[1] @ x + R[1] @ self.y + p[0] * self.c + b[1])  # eq. (10) input gate
        f = _sigmoid(W[2] @ x + R[2] @ self.y + p[1] * self.c + b[2])  # eq. (11) forget gate (its own bias b_f)
        c = z * i + self.c * f  # eq. (12) cell
        o = _sigmoid(W[3] @ x + R[3] @ self.y + p[2] * c + b[3])  # eq. (13) output gate, peephole on the new cell
        self.y = np.tanh(c) * o  # eq. (14) block output
        self.c = c
        a = 1.0 + 0.5 * self.y  # (-1, 1) -> (0.5, 1.5)
        return float(a[0]), float(a[1])


@dataclass
class Coordination:
    """One agent's MRC output for this step."""

    alpha: float
    v: float  # eq. (2), bounded
    beta: float  # eq. (8); 0 when no adjustment
    adjust: bool  # eq. (7) applies (TS only; the caller checks the behaviour)
    rank: int  # 1-based
    n: int
    inputs: np.ndarray  # FLC_SR's normalised inputs


class Coordinator:
    """Decentralised MRC: ``coordinator`` is an :class:`FlcSr`, an :class:`LstmMrc` or None (no MRC)."""

    def __init__(self, coordinator, cfg: MrcConfig | None = None):
        self.cfg = cfg or MrcConfig()
        self.coordinator = coordinator
        self.reset()

    def reset(self) -> None:
        self.v = self.cfg.v0
        if self.coordinator is not None:
            self.coordinator.reset()

    def inputs(self, d_sorted: np.ndarray, v_sorted: np.ndarray) -> np.ndarray:
        c = self.cfg
        return np.array([d_sorted[0] / c.d_scale, d_sorted[-1] / c.d_scale, v_sorted[0] / c.v_scale,
                         v_sorted[-1] / c.v_scale, (d_sorted[-1] - d_sorted[0]) / c.d_scale])

    def step(self, d_own: float, peers: list[PeerEstimate]) -> Coordination:
        """Rank self and peers by distance to the target, eq. (1)-(2) and (8) for this robot."""
        c = self.cfg
        if self.coordinator is None:  # no MRC: constant speed, straight to the goal
            self.v = c.v0
            return Coordination(1.0, self.v, 0.0, False, 1, 1, np.zeros(5))
        ps = [p for p in peers if p.age <= c.max_age]
        # a stale peer has moved on since: extrapolate its distance along its speed (at most toward 0)
        d = np.array([d_own] + [max(0.0, p.d_goal - p.v * p.age) for p in ps])
        v = np.array([self.v] + [p.v for p in ps])
        order = np.argsort(d, kind="stable")
        n = len(d)
        rank = int(np.nonzero(order == 0)[0][0]) + 1
        x = self.inputs(d[order], v[order])
        if n == 1:
            alpha = 1.0
            self.coordinator(x)  # keep a recurrent coordinator's memory in step
        else:
            a1, an = self.coordinator(x)
            a1, an = min(a1, an), max(a1, an)  # the farthest robot never gets the smaller factor
            alpha = float(interpolate_alphas(a1, an, n)[rank - 1])
        self.v = float(np.clip(alpha * self.v, c.v_min, c.v_max))  # eq. (2), bounded
        d_n = float(d.max())
        adjust = n > 1 and rank < n and (d_n - d.min()) >= c.delta_d_stop and d_n > c.d_near_all
        b = beta(alpha, d_own, d_n) if adjust else 0.0
        v_out = self.v
        if c.terminal_match and n > 1 and rank < n and 0.0 < d_n <= c.d_near_all:
            v_n = float(v[order][-1])  # the farthest robot's speed: match its time to go, d_n / v_n
            v_out = float(np.clip(min(self.v, v_n * d_own / d_n), c.v_min, c.v_max))
        return Coordination(alpha, v_out, b, adjust, rank, n, x)

    def theta_adj(self, theta_goal: float, co: Coordination) -> float:
        """Eq. (7)."""
        return theta_goal + co.beta * self.cfg.theta_max_adj if co.adjust else theta_goal
