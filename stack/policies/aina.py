"""Artificial immune network steering + position tracking (Deng, Ma, Gu, Li, Xu, Wang; IJRA 2016).

The steering direction comes from an immune network (section 3); a follower's linear speed
from the position tracking law (section 4). Names follow the paper:

  antibodies   Ab_s = theta_s = 2 pi (s - 1) / N_Ab, s = 1..N_Ab  (steering directions, world frame)
  eq. (4)      dA_s/dt = ( sum_s1 cos(theta_s - theta_s1) a_s1 + m_s - k_s ) a_s
  eq. (5)      a_s = 1 / (1 + exp(0.5 - A_s))
  eq. (6)      m_s = tau1 F_goal1 + tau2 F_goal2 + tau3 F_obs            (follower)
  eq. (7)      F_goal1 = (1 + cos(theta_s - theta_i)) / 2                 (leader's steering direction)
  eq. (8)      F_goal2 = (1 + cos(theta_s - theta_gv)) / 2                (azimuth of the virtual robot)
  eq. (9)      F_obs   (obstacle term, see below)
  eq. (10)     m_s = mu1 F_goal + mu2 F_obs                               (leader)
  eq. (11)     E = [e_x, e_y] = R(theta_j) [x_v - x_j, y_v - y_j]
  eq. (13)     v_j = v_i cos(theta_i - theta_j) + K1 e_x - K2 e_y

**Eq. (9) as we read it.** The printed formula is garbled
(``F_obs = sum_f exp^{N_Ab} . d_f . (1 + cos(theta_s - theta_Sf)) / 2``). What survives is:
a sum over the N_S sensors, an exponential, the normalised distance d_f of sensor f and a
raised-cosine lobe around the sensor's azimuth theta_Sf; the text calls F_obs "the repulsion
of the s-th antibody from obstacles". In Luh and Liu's reactive immune network (the paper's
reference [15]) the obstacle antigen likewise stimulates each antibody through such a lobe
per sensor, weighted by how near the obstacle is, and a sensor that sees nothing adds
nothing. We read eq. (9) as

    F_obs = - sum_f ( exp(kappa (1 - d_f)) - 1 ) * ((1 + cos(theta_s - theta_Sf)) / 2) ** N_Ab,
    d_f = min(clearance_f, d_max) / d_max  in [0, 1]

- a repulsion (negative: it lowers the affinity of directions that point at an obstacle,
  since tau3 > 0 multiplies it in eq. 6), zero for a sensor that sees nothing (d_f = 1),
  growing exponentially as the obstacle nears (the surviving ``exp``);
- the exponent on the lobe (the surviving superscript N_Ab) narrows each sensor's lobe to
  about its own sector (with N_Ab = 36 the lobe is 0.76 one antibody, 10 degrees, away and
  0.25 at 22.5 degrees, the spacing of eight sectors over a 180-degree lidar), so an obstacle
  ahead does not repel the directions beside it.
The reading that the term is instead a bounded attraction toward free space cannot avoid
anything with the paper's tau3 = 0.1: an antibody 45 degrees off the goal loses
0.9 (1 - cos 45) / 2 = 0.13 of goal affinity, more than the 0.1 the obstacle term could give
back, so the robot would drive into an obstacle on its path. The test suite shows ours does
avoid (``tests/test_aina.py``).

**Choices where the paper is silent** (all in :class:`AinaConfig`):
- the idiotypic sum of eq. (4) is divided by N_Ab, so the network's behaviour does not
  depend on how many antibodies there are;
- eq. (4) is integrated with ``n_iter`` Euler steps of ``h`` per control step, starting from
  the previous step's A_s times ``memory`` (the network keeps some hysteresis between steps);
- Algorithm 1: the best ``n_top`` antibodies by concentration are cloned, each in proportion
  to its affinity m_s (q_c clones), the clones' directions are coded as ``bits``-bit genes,
  paired for a one-point crossover and mutated bit by bit with ``p_mutation``; each new
  antibody's concentration is computed with eq. (4)-(5) against the network's field, and the
  highest concentration among old and new antibodies wins (selection);
- sensors: the lidar is cut into N_S equal sectors across its field of view; a sector's
  range is its shortest beam minus the robot radius (the sonar measures from the hull).
  "The adjacent robot within the detection radius is considered as an obstacle": a beam that
  ends on a known neighbour counts only within ``robot_detect`` metres of clearance;
- steering direction -> angular velocity: w = k_heading wrap(theta* - theta_j) (the driver
  clamps to w_max);
- the bound of section 4.1, v_j <= min(V_max, |p_v - p_j| / t), is read with t the control
  period and relative to the virtual robot's own motion: v_j <= min(V_max, max(0, v_i
  cos(theta_i - theta_j)) + |p_v - p_j| / dt), so the follower never overshoots its virtual
  robot within a step yet can keep pace with it; v_j >= 0 (our bases do not reverse). Both
  keep the Lyapunov derivative of section 4.2 non-positive (see ``lyapunov_derivative``);
- the paper's robots (Matlab spheres) move in any direction; ours are unicycles, so both
  roles multiply their speed by max(0, cos(theta* - theta_j)): a robot turns toward the
  chosen direction before it speeds along it (without this a follower whose network steers
  it away from an obstacle would still drive at the eq. (13) speed along its old heading).
  Eq. (13) and its bounds stay as they are (``tracking_speed``; section 4.2's derivative is
  checked on that law in the tests);
- the leader (section 3.2) drives at its constant speed ``v_leader`` v_max and slows to
  d_g / (1 s) near the goal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..estimation.pose import wrap as _wrap
from ..settings import check, rule
from .base import Observation, Policy

TWO_PI = 2.0 * math.pi

_COUNT = rule(">= 1", "<= 3600")
_FRACTION = rule(">= 0", "<= 1")


@dataclass(frozen=True)
class AinaConfig:
    """``robot.aina``: parameters of the immune-network policy (Deng et al.)."""

    RULE = (">= 0",)

    n_ab: int = field(default=36, metadata=_COUNT)
    """N_Ab antibodies, the steering directions 2 pi (s - 1) / N_Ab."""
    n_s: int = field(default=8, metadata=_COUNT)
    """N_S virtual range sensors (lidar sectors), like the AmigoBot's eight sonars."""
    tau1: float = 0.4
    """Eq. (6): weight of the leader's steering direction (tau1 + tau2 + tau3 = 1)."""
    tau2: float = 0.5
    """Eq. (6): weight of the virtual robot's azimuth."""
    tau3: float = 0.1
    """Eq. (6): weight of the obstacle term."""
    mu1: float = 0.5
    """Eq. (10): the leader's goal weight (mu1 + mu2 = 1)."""
    mu2: float = 0.5
    """Eq. (10): the leader's obstacle weight."""
    k_s: float = 0.5
    """Eq. (4): natural death coefficient."""
    kappa: float = 4.0
    """Eq. (9) as read here: steepness of the repulsion over the normalised distance."""
    k1: float = 0.3
    """Eq. (13): K1 [1/s]."""
    k2: float = 0.08
    """Eq. (13): K2 [1/s]."""
    v_leader: float = field(default=0.6, metadata=_FRACTION)
    """The leader's constant speed (section 3.2), a fraction of v_max."""
    k_heading: float = 2.0
    """Steering-direction error -> angular velocity [1/s]."""
    robot_detect: float = 1.0
    """[m] a neighbour is an obstacle within this clearance (the paper's "detection radius")."""
    clones: int = field(default=12, metadata=_COUNT)
    """Algorithm 1: clones made each step."""
    p_mutation: float = field(default=0.1, metadata=_FRACTION)
    """Algorithm 1: probability that one gene (bit) flips."""

    def __post_init__(self):
        check(self)
        if abs(self.tau1 + self.tau2 + self.tau3 - 1.0) > 1e-6:
            raise ValueError(f"tau1 + tau2 + tau3 must be 1 (eq. 6), got {self.tau1 + self.tau2 + self.tau3:g}")
        if abs(self.mu1 + self.mu2 - 1.0) > 1e-6:
            raise ValueError(f"mu1 + mu2 must be 1 (eq. 10), got {self.mu1 + self.mu2:g}")


def _sigmoid(A: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(0.5 - A))  # eq. (5)


def lobe(theta: np.ndarray, theta_ref, power: float = 1.0) -> np.ndarray:
    """(1 + cos(theta - theta_ref)) / 2, raised to ``power``: the attraction shape of eq. (7)-(9)."""
    return ((1.0 + np.cos(theta - theta_ref)) / 2.0) ** power


@dataclass
class Antigen:
    """What the network sees at one step (all angles world frame, radians).

    theta_i: the leader's steering direction (followers only; None for the leader).
    theta_g: azimuth of the target: the virtual robot theta_gv for a follower, the goal for the leader.
    d_bar: (N_S,) normalised obstacle distances of the sensors, 1 = nothing seen.
    theta_S: (N_S,) azimuths of the sensors.
    """

    theta_g: float
    d_bar: np.ndarray
    theta_S: np.ndarray
    theta_i: float | None = None


class ImmuneNetwork:
    """Eq. (4)-(10) and Algorithm 1: the steering direction with the highest concentration."""

    def __init__(self, n_ab: int = 36, n_s: int = 8, *, tau=(0.4, 0.5, 0.1), mu=(0.5, 0.5), k_s: float = 0.5,
                 kappa: float = 4.0, clones: int = 12, n_top: int = 3, bits: int = 10, p_mutation: float = 0.1,
                 n_iter: int = 10, h: float = 0.2, memory: float = 0.5, rng: np.random.Generator | None = None):
        self.N_Ab, self.N_S = n_ab, n_s
        self.tau, self.mu, self.k_s, self.kappa = tau, mu, k_s, kappa
        self.clones, self.n_top, self.bits, self.p_mutation = clones, min(n_top, n_ab), bits, p_mutation
        self.n_iter, self.h, self.memory = n_iter, h, memory
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.theta = TWO_PI * np.arange(n_ab) / n_ab  # Ab_s = theta_s = 2 pi (s - 1) / N_Ab
        self.A = np.zeros(n_ab)
        self.a = _sigmoid(self.A)
        self.last_offspring = np.zeros(0)

    def reset(self) -> None:
        self.A[:] = 0.0
        self.a = _sigmoid(self.A)

    # --- affinities --------------------------------------------------------------------
    def F_obs(self, theta: np.ndarray, ag: Antigen) -> np.ndarray:
        """Eq. (9) as read in the module docstring: exponential repulsion through narrow lobes."""
        push = np.exp(self.kappa * (1.0 - np.clip(ag.d_bar, 0.0, 1.0))) - 1.0  # zero for a sensor that sees nothing
        return -(push[None, :] * lobe(theta[:, None], ag.theta_S[None, :], self.N_Ab)).sum(axis=1)

    def affinity(self, theta: np.ndarray, ag: Antigen) -> np.ndarray:
        """m_s for directions ``theta``: eq. (6) for a follower (theta_i given), eq. (10) for the leader."""
        if ag.theta_i is not None:
            tau1, tau2, tau3 = self.tau
            F_goal1 = lobe(theta, ag.theta_i)  # eq. (7)
            F_goal2 = lobe(theta, ag.theta_g)  # eq. (8)
            return tau1 * F_goal1 + tau2 * F_goal2 + tau3 * self.F_obs(theta, ag)  # eq. (6)
        mu1, mu2 = self.mu
        F_goal = lobe(theta, ag.theta_g)
        return mu1 * F_goal + mu2 * self.F_obs(theta, ag)  # eq. (10)

    # --- concentrations ----------------------------------------------------------------
    def _stimulation(self, theta: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Idiotypic term of eq. (4): sum_s1 cos(theta - theta_s1) a_s1, divided by N_Ab."""
        return np.cos(theta[:, None] - self.theta[None, :]) @ a / self.N_Ab

    def _integrate(self, A: np.ndarray, theta: np.ndarray, m: np.ndarray, field_a: list[np.ndarray] | None):
        """Euler steps of eq. (4); the network's own antibodies (field_a None) or new ones in its field."""
        history = []
        a = _sigmoid(A)
        for it in range(self.n_iter):
            src = a if field_a is None else field_a[it]
            if field_a is None:
                history.append(a)
            dA = (self._stimulation(theta, src) + m - self.k_s) * a  # eq. (4)
            A = A + self.h * dA
            a = _sigmoid(A)  # eq. (5)
        return A, a, history

    def step(self, ag: Antigen) -> float:
        """One control step: integrate eq. (4)-(5), run Algorithm 1, return the chosen direction."""
        m = self.affinity(self.theta, ag)
        A_start = self.memory * self.A
        self.A, self.a, field = self._integrate(A_start, self.theta, m, None)

        # Algorithm 1. Clonal operator: the best antibodies by concentration, q_c clones each in
        # proportion to their affinity with the antigen.
        top = np.argsort(-self.a, kind="stable")[: self.n_top]
        w = np.maximum(m[top] - m[top].min(), 0.0) + 1e-9
        q_c = np.maximum(1, np.round(self.clones * w / w.sum()).astype(int))
        n_codes = 1 << self.bits
        genes = np.repeat(np.round(self.theta[top] / TWO_PI * n_codes).astype(np.int64) % n_codes, q_c)
        # Crossover operator: pairs of clones swap their genes below a random cut point.
        self.rng.shuffle(genes)
        if len(genes) >= 2:
            half = len(genes) // 2
            g1, g2 = genes[:half].copy(), genes[half: 2 * half].copy()
            cut = self.rng.integers(1, self.bits, half)
            low = (np.int64(1) << cut) - 1
            genes[:half] = (g1 & ~low) | (g2 & low)
            genes[half: 2 * half] = (g2 & ~low) | (g1 & low)
        # Mutation operator: each gene (bit) flips 0 -> 1 or 1 -> 0 with probability p_mutation.
        flips = self.rng.random((len(genes), self.bits)) < self.p_mutation
        genes ^= (flips * (np.int64(1) << np.arange(self.bits))).sum(axis=1)
        offspring = (genes % n_codes) * TWO_PI / n_codes
        self.last_offspring = offspring
        # Their concentrations by eq. (4)-(5) in the network's field, from the same start.
        A0 = np.interp(offspring, self.theta, A_start, period=TWO_PI)
        _, a_new, _ = self._integrate(A0, offspring, self.affinity(offspring, ag), field)
        # Selection operator: the antibody with the highest concentration.
        i = int(np.argmax(self.a))
        j = int(np.argmax(a_new)) if len(a_new) else -1
        if j >= 0 and a_new[j] > self.a[i]:
            return float(offspring[j])
        return float(self.theta[i])


def sectors(ranges: np.ndarray, fov: float, n_s: int, *, radius: float, d_max: float,
            neighbours: np.ndarray | None = None, robot_detect: float = 1.0):
    """N_S virtual range sensors from one lidar scan (robot frame).

    Returns (d_bar, angles): per sector the normalised clearance (1 = nothing within d_max)
    and the sector's centre angle. Beams that end on a known neighbour ([distance, bearing]
    rows) count only within ``robot_detect`` of clearance.
    """
    n = len(ranges)
    ang = np.linspace(-fov / 2, fov / 2, n) if n > 1 else np.zeros(1)
    clear = np.asarray(ranges, float) - radius
    scale = np.full(n, d_max)
    if neighbours is not None and len(neighbours):
        ex, ey = ranges * np.cos(ang), ranges * np.sin(ang)
        nx, ny = neighbours[:, 0] * np.cos(neighbours[:, 1]), neighbours[:, 0] * np.sin(neighbours[:, 1])
        on_robot = (np.hypot(ex[:, None] - nx[None, :], ey[:, None] - ny[None, :]) < radius + 0.3).any(axis=1)
        scale = np.where(on_robot, robot_detect, d_max)
    d_bar = np.clip(clear / scale, 0.0, 1.0)
    edges = np.linspace(0, n, n_s + 1).round().astype(int)
    out = np.ones(n_s)
    for f in range(n_s):
        seg = d_bar[edges[f]: max(edges[f + 1], edges[f] + 1)]
        out[f] = seg.min() if len(seg) else 1.0
    centres = -fov / 2 + fov * (np.arange(n_s) + 0.5) / n_s
    return out, centres


def tracking_speed(e_x: float, e_y: float, v_i: float, theta_i: float, theta_j: float, *, K1: float, K2: float,
                   V_max: float, dt: float) -> float:
    """Eq. (13), bounded as in section 4.1 (read as in the module docstring)."""
    c = math.cos(theta_i - theta_j)
    v_j = v_i * c + K1 * e_x - K2 * e_y  # eq. (13)
    dist = math.hypot(e_x, e_y)
    return max(0.0, min(v_j, V_max, max(0.0, v_i * c) + dist / dt))


def lyapunov_derivative(e_x: float, e_y: float, v_i: float, theta_i: float, theta_j: float, v_j: float,
                        K1: float, K2: float) -> float:
    """Section 4.2: dV/dt = K1 e_x (cos(theta_i - theta_j) v_i - v_j) + K2 e_y (-cos(theta_i - theta_j) v_i + v_j)."""
    c = math.cos(theta_i - theta_j)
    return K1 * e_x * (c * v_i - v_j) + K2 * e_y * (-c * v_i + v_j)


class AinaPolicy(Policy):
    """``--policy aina``: eq. (6) steering + eq. (13) speed for a follower, eq. (10) for the leader."""

    name = "aina"
    hybrid = False  # not a network inside Bai's hybrid switch: this policy drives in every situation

    def __init__(self, cfg: AinaConfig, *, role: str, radius: float, v_max: float, lidar_fov: float, lidar_range: float,
                 seed: int = 0):
        self.cfg = cfg
        self.role = role
        self.radius = radius
        self.v_max = v_max
        self.fov = lidar_fov
        self.d_max = max(lidar_range - radius, 1e-3)
        self.net = ImmuneNetwork(cfg.n_ab, cfg.n_s, tau=(cfg.tau1, cfg.tau2, cfg.tau3), mu=(cfg.mu1, cfg.mu2),
                                 k_s=cfg.k_s, kappa=cfg.kappa, clones=cfg.clones, p_mutation=cfg.p_mutation,
                                 rng=np.random.default_rng(seed))
        self.last: dict[str, float] = {}

    def reset(self) -> None:
        self.net.reset()

    def antigen(self, obs: Observation) -> Antigen:
        scan = obs.scans[-1] if obs.scans.size else np.zeros(0)
        if scan.size:
            d_bar, centres = sectors(scan, self.fov, self.cfg.n_s, radius=self.radius, d_max=self.d_max,
                                     neighbours=obs.neighbours, robot_detect=self.cfg.robot_detect)
        else:
            d_bar, centres = np.ones(self.cfg.n_s), np.zeros(self.cfg.n_s)
        theta_g = obs.yaw + obs.alpha_g  # azimuth of the virtual robot (follower) or the goal (leader)
        if self.role == "leader":
            return Antigen(theta_g=theta_g, d_bar=d_bar, theta_S=obs.yaw + centres)
        theta_i = obs.target_yaw if obs.target_yaw is not None else theta_g
        return Antigen(theta_g=theta_g, d_bar=d_bar, theta_S=obs.yaw + centres, theta_i=theta_i)

    def act(self, obs: Observation) -> tuple[float, float]:
        cfg = self.cfg
        ag = self.antigen(obs)
        theta_star = self.net.step(ag)
        err = float(_wrap(theta_star - obs.yaw))
        w = cfg.k_heading * err
        if self.role == "leader":
            v_c = cfg.v_leader * self.v_max
            v = min(v_c * max(0.0, math.cos(err)), obs.d_g)  # constant speed; d_g / 1 s within v_c of the goal
            if obs.d_g < 0.05:
                v, w = 0.0, 0.0
            self.last = {"theta": theta_star, "v": v, "w": w}
            return v, w
        # follower: E in the follower's frame (eq. 11) is the virtual robot's position seen from the robot
        e_x, e_y = obs.d_g * math.cos(obs.alpha_g), obs.d_g * math.sin(obs.alpha_g)
        gvx, gvy = obs.goal_velocity
        v_i = math.hypot(gvx, gvy)
        theta_i = ag.theta_i
        v_13 = tracking_speed(e_x, e_y, v_i, theta_i, obs.yaw, K1=cfg.k1, K2=cfg.k2, V_max=self.v_max, dt=obs.dt)
        v = v_13 * max(0.0, math.cos(err))  # a unicycle turns toward theta* before it speeds along it
        self.last = {"theta": theta_star, "v": v, "v_13": v_13, "w": w, "e_x": e_x, "e_y": e_y, "v_i": v_i,
                     "theta_i": theta_i}
        return v, w


def make_aina(robot, *, seed: int = 0, **_) -> AinaPolicy:
    """Factory: ``robot.aina`` (:class:`AinaConfig`), the robot's role, radius, speed and lidar."""
    return AinaPolicy(robot.config_for("aina"), role=robot.role or "leader", radius=robot.radius, v_max=robot.v_max,
                      lidar_fov=robot.lidar.fov, lidar_range=robot.lidar.range, seed=seed)
