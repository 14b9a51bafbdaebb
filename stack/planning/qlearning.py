"""Improved Q-learning of Fan et al. 2021 (section 3, Algorithms 1-2, Table 1): the five variants Q-L1..Q-L5.

=========  ==========================================================================
Q-L1       Algorithm 1: classic Q-learning, eq. (1), fixed epsilon-greedy eq. (2), Q = 0
Q-L2       Q-L1 with the simulated-annealing greedy factor, eq. (10)-(11)
Q-L3       Q-L2 with the GPF Q-initialisation ("environmental guidance"), eq. (8)-(9)
Q-L4       Algorithm 2: Q-L3 with virtual obstacle filling (section 3.2)
Q-L5       Q-L4 with the reward r2 of eq. (14) (a small penalty per step)
=========  ==========================================================================

Entry point: :func:`plan` (any boolean occupancy ``[x, y]`` + start + goal cells; see
:mod:`stack.planning.grid` for the conventions) or :func:`plan_map` (a parsed map). Replanning on
a changed grid is cheap with ``warm_start=previous_result``: Q rows and virtual obstacles away from
the changed cells are kept (within one cell of a change they are dropped and initialised again).

Readings of the paper where it is ambiguous or silent (the choices made here):

1. Rounds (episodes) start at the start cell and end only at the goal, as the loops of Algorithms
   1-2 say ("while s_t != target state"): a step into an obstacle (real or virtual), off the map or
   clipping a corner (see ``grid``) gives r = -1 and the robot stays where it is. The paper gives
   no step limit; a round is cut after ``max_steps`` (default: the number of grid cells) steps,
   which only matters while the robot is lost or trapped. ``collision="terminal"`` ends the round
   at a collision instead (the "hell" cells of the Tkinter maze tutorials); with the fixed epsilon
   of Q-L1 and Q = 0 the robot then never lives long enough to reach a far goal, whereas the paper
   reports Q-L1 converging, so the default is "stay".
2. Algorithm 1 lists four actions; section 4.2 and Table 2 (18 diagonal steps in Q-L1's 37.46)
   use eight, so every variant has the eight actions of Algorithm 2.
3. eq. (9) is used as written in Algorithm 2 step (1): ``U'_gra`` is taken at the successor s' of
   (s, a) (at s, all eight actions would get the same value), and r_q is what the 3 x 3 sensor
   reads at s' (+1 goal, -1 obstacle/virtual obstacle/off-grid, 0 free). The row of a state is
   initialised when the robot first stands on it (its sensor then sees all eight successors);
   rows are never re-initialised when a neighbour is filled later. d_aim is in pixels of the
   paper's canvas (26 px a cell, section 5.1): eta = 735 is then the map's diagonal (520 sqrt 2),
   U' spans [-5, 0] and one cell changes Q by 0.01-0.03; in cells, eq. (8) would be nearly flat.
4. SA (Algorithm 2): every n rounds, at the start state, T is set by eq. (10) from the step counts
   of the last n rounds (T = T0 for the first n) and epsilon by eq. (11) with one random action;
   epsilon is then used as in eq. (2) for the next n rounds. Sample std (n - 1), as eq. (10).
5. Convergence: the last 10 rounds all reached the goal and the sample std of their step counts is
   below 5 (a trapped robot cut at ``max_steps`` every round would otherwise look "converged").
   ``convergence_round`` is the 1-based index of that 10th round; training stops there
   (``stop_at_convergence``). The time is wall time from the start of :func:`plan`.
6. Greedy ties are broken uniformly at random (essential for Q = 0 in Q-L1/Q-L2).
7. The planned path (``path``, ``steps``, ``path_length``; Fig. 5, Table 2) is the epsilon = 0
   rollout of the final Q-table on the final grid, over the steps the 3 x 3 sensor allows (a row
   initialised before a neighbour was filled may still rank the bump first; ties: lowest action
   index), if it reaches the goal; else the last round's cells, loops erased if that round reached
   the goal, raw if not (Q-L3 trapped). ``last_round_path`` is kept as it was walked.
8. Filling (Q-L4/Q-L5) is tested at every step, before the action is chosen (Algorithm 2 step (3)),
   on cells (real and virtual obstacles, off-grid); the goal is never filled. It can wall the start
   in when the way to the goal first leads away from it; ``fill_guard=True`` (ours) prevents that.

Deterministic for a given ``seed`` (one ``numpy.random.Generator``); only the times vary.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from .grid import ACTIONS, STEP_LENGTH, Cell, GridMap, GridWorld, check_cells

VARIANTS: tuple[str, ...] = ("Q-L1", "Q-L2", "Q-L3", "Q-L4", "Q-L5")

#: Table 1 / Table 2: which improvements each variant has.
FEATURES: dict[str, dict] = {
    "Q-L1": dict(sa=False, gpf=False, filling=False, reward="r1"),
    "Q-L2": dict(sa=True, gpf=False, filling=False, reward="r1"),
    "Q-L3": dict(sa=True, gpf=True, filling=False, reward="r1"),
    "Q-L4": dict(sa=True, gpf=True, filling=True, reward="r1"),
    "Q-L5": dict(sa=True, gpf=True, filling=True, reward="r2"),
}

#: eq. (14): rewards (reach the target, any other step, hit an obstacle).
REWARDS: dict[str, tuple[float, float, float]] = {"r1": (1.0, 0.0, -1.0), "r2": (1.0, -0.05, -1.0)}


@dataclass
class QLearningConfig:
    """Arguments of the learner; defaults are section 5.1's."""

    variant: str = "Q-L5"
    """One of Q-L1..Q-L5 (Table 1); sets ``sa``, ``gpf``, ``filling`` and ``reward`` unless given."""
    seed: int = 0
    """Seed of the one ``numpy.random.Generator`` (exploration and tie-breaking)."""
    alpha: float = 0.01
    """Learning rate alpha of eq. (1)."""
    gamma: float = 0.9
    """Discount factor gamma of eq. (1) and eq. (9)."""
    epsilon: float = 0.2
    """Fixed greedy factor epsilon of eq. (2) (variants without SA)."""
    T0: float = 10.0
    """Initial SA temperature (used for the first n rounds)."""
    n: int = 10
    """Number of consecutive rounds of eq. (10); epsilon is recomputed every n rounds."""
    i: float = 0.1
    """Small constant i of eq. (10), keeps T > 0 after convergence."""
    k: float = 0.03
    """Control factor k of eq. (10)."""
    q: float = 1.0
    """Non-zero constant q of eq. (11)."""
    xi: float = -10.0
    """GPF factor xi of eq. (8) (negative)."""
    eta: float = 735.0
    """Positive constant eta of eq. (8), in pixels (735 = the diagonal of the paper's 20 x 20 map of
    26 px cells: 520 * sqrt(2) = 735.4)."""
    cell_px: float = 26.0
    """Pixels per cell: d_aim of eq. (8) is measured on the paper's Tkinter canvas, 26 x 26 px a cell
    (section 5.1). With d in cells, eq. (8) would be almost flat (U' in [-0.35, 0] on 20 x 20)."""
    k_q: float = 0.1
    """Scale coefficient k_q of eq. (9)."""
    max_rounds: int = 10000
    """Most rounds (episodes, m of Algorithms 1-2)."""
    conv_rounds: int = 10
    """Convergence: this many consecutive rounds ..."""
    conv_std: float = 5.0
    """... whose step counts have a sample std below this (section 5.1)."""
    max_steps: int | None = None
    """Most steps in one round (paper: not given); None = number of grid cells."""
    collision: str = "stay"
    """What a collision does: "stay" keeps the robot in place, the round goes on (reading 1);
    "terminal" ends the round."""
    corner_cutting: bool = False
    """Allow diagonal steps past a blocked orthogonal cell (see :mod:`.grid`)."""
    fill_guard: bool = False
    """Not in the paper: skip a fill that would cut the start off from the goal (section 3.2 fills the
    whole shadow of a wall facing the goal, start included, when the way round first leads away)."""
    stop_at_convergence: bool = True
    """Stop training at the convergence round (else run all ``max_rounds``)."""
    sa: bool | None = None
    """Simulated-annealing epsilon, eq. (10)-(11); None = from ``variant``."""
    gpf: bool | None = None
    """GPF Q-initialisation, eq. (8)-(9); None = from ``variant``."""
    filling: bool | None = None
    """Virtual obstacle filling, section 3.2; None = from ``variant``."""
    reward: str | None = None
    """"r1" or "r2" of eq. (14); None = from ``variant``."""

    def resolved(self) -> "QLearningConfig":
        """A copy with the variant's features filled in and the arguments checked."""
        if self.variant not in FEATURES:
            raise ValueError(f"unknown variant {self.variant!r}; expected one of {', '.join(VARIANTS)}")
        d = asdict(self)
        for key, val in FEATURES[self.variant].items():
            if d[key] is None:
                d[key] = val
        c = QLearningConfig(**d)
        if c.reward not in REWARDS:
            raise ValueError(f"reward must be r1 or r2, got {c.reward!r}")
        if c.collision not in ("terminal", "stay"):
            raise ValueError(f"collision must be 'terminal' or 'stay', got {c.collision!r}")
        if not (0 < c.alpha < 1 and 0 < c.gamma < 1 and 0 <= c.epsilon <= 1):
            raise ValueError("need 0 < alpha < 1, 0 < gamma < 1, 0 <= epsilon <= 1")
        if c.n < 2 or c.conv_rounds < 2 or c.max_rounds < 1:
            raise ValueError("need n >= 2, conv_rounds >= 2, max_rounds >= 1")
        if c.T0 <= 0 or c.i <= 0 or c.eta <= 0:
            raise ValueError("need T0 > 0, i > 0, eta > 0")
        return c


@dataclass
class QLearningResult:
    """What :func:`plan` learned and measured."""

    variant: str
    seed: int
    converged: bool
    convergence_round: int | None
    convergence_time_s: float | None
    rounds: int
    """Rounds run."""
    time_s: float
    """Wall time of the whole run."""
    last_round_path: list[Cell]
    """Cells of the last round (at convergence: the converged round); bumps repeat a cell."""
    reached: bool
    """Whether the last round reached the goal."""
    greedy_path: list[Cell]
    """epsilon = 0 rollout of the final Q-table (stops at the goal, a collision or a repeated cell)."""
    greedy_reached: bool
    steps_per_round: list[int]
    reward_per_round: list[float]
    epsilon_per_round: list[float]
    occupancy: np.ndarray = field(repr=False)
    virtual: np.ndarray = field(repr=False)
    Q: np.ndarray = field(repr=False)
    """Q-table, shape (nx * ny, 8); rows of states never initialised are NaN."""
    start: Cell = (0, 0)
    goal: Cell = (0, 0)
    warm_started: bool = False

    @property
    def path(self) -> list[Cell]:
        """The planned path (reading 7): the greedy rollout if it reaches the goal, else the last round's
        cells, with bumps and loops erased if that round reached the goal."""
        if self.greedy_reached:
            return self.greedy_path
        return _erase_loops(self.last_round_path) if self.reached else self.last_round_path

    @property
    def steps(self) -> int:
        return len(self.path) - 1

    @property
    def path_length(self) -> float:
        return _length(self.path)

    def summary(self) -> dict:
        """JSON-ready fields (the ``qlearn.json`` contract and more)."""
        return {
            "variant": self.variant, "seed": self.seed, "converged": self.converged,
            "convergence_round": self.convergence_round,
            "convergence_time_s": None if self.convergence_time_s is None else round(self.convergence_time_s, 6),
            "steps": self.steps, "path_length": round(self.path_length, 4), "path": [list(c) for c in self.path],
            "path_reaches_goal": self.greedy_reached or self.reached,
            "last_round_steps": len(self.last_round_path) - 1,
            "last_round_path_length": round(_length(self.last_round_path), 4), "last_round_reached": self.reached,
            "rounds": self.rounds, "time_s": round(self.time_s, 6),
            "virtual_obstacles": [list(map(int, c)) for c in np.argwhere(self.virtual)],
            "start": list(self.start), "goal": list(self.goal), "warm_started": self.warm_started,
        }


def _erase_loops(path: list[Cell]) -> list[Cell]:
    out: list[Cell] = []
    where: dict[Cell, int] = {}
    for c in path:
        if c in where:  # back to a cell already on the path: drop the loop
            for d in out[where[c] + 1:]:
                del where[d]
            del out[where[c] + 1:]
        else:
            where[c] = len(out)
            out.append(c)
    return out


def _length(path) -> float:
    return float(sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(path, path[1:])))


# ---------------------------------------------------------------- the equations, one function each

def gpf(d, xi: float = -10.0, eta: float = 735.0):
    """eq. (8): U'_gra(s) = xi * d_aim(s) / (d_aim(s) + eta)."""
    return xi * d / (d + eta)


def gpf_q_init(d_next, r_q, k_q: float = 0.1, gamma: float = 0.9, xi: float = -10.0, eta: float = 735.0):
    """eq. (9): Q(s, a) = k_q * (r_q + gamma * U'_gra(s')), s' the successor of (s, a) (Algorithm 2 step (1))."""
    return k_q * (r_q + gamma * gpf(d_next, xi, eta))


def sa_temperature(steps, i: float = 0.1, k: float = 0.03) -> float:
    """eq. (10): T = i + k * sample std of the step numbers of n consecutive rounds."""
    s = np.asarray(steps, dtype=float)
    return float(i + k * np.sqrt(((s - s.mean()) ** 2).sum() / (len(s) - 1)))


def sa_epsilon(q_random: float, q_max: float, q: float = 1.0, T: float = 10.0) -> float:
    """eq. (11): epsilon = exp((Q(s, a_random) - Q(s, a_max) - q) / T) (the Metropolis acceptance, eq. (7))."""
    return math.exp((q_random - q_max - q) / T)


def _uniforms(rng: np.random.Generator, block: int = 1 << 15):
    while True:
        yield from rng.random(block).tolist()


class GPFInit:
    """Algorithm 2 step (1): the Q row of a state the robot stands on for the first time, eq. (9).

    ``GPFInit(world, config)(s)`` -> 8 values ``k_q * (r_q + gamma * U'_gra(s'))``, with s' the successor
    of each action, d_aim(s') in pixels (``cell_px``; off-grid successors by their coordinates) and
    r_q what the 3 x 3 sensor reads at s' now: +1 the goal, -1 an obstacle, virtual obstacle,
    off-grid cell or clipped corner, 0 free. The GPF part is computed once for the whole grid.
    """

    def __init__(self, world: GridWorld, c: QLearningConfig):
        gx, gy = world.goal
        xs, ys = np.divmod(np.arange(world.n_states), world.ny)
        d_next = c.cell_px * np.stack([np.hypot(xs + dx - gx, ys + dy - gy) for dx, dy in ACTIONS], axis=1)
        self.base = gpf_q_init(d_next, 0.0, c.k_q, c.gamma, c.xi, c.eta).tolist()  # eq. (9) with r_q = 0
        self.goal_next = [[t == world.s_goal for t in row] for row in world.nxt]
        self.ok = world.ok
        self.k_q = c.k_q

    def __call__(self, s: int) -> list[float]:
        b, okr, gn, kq = self.base[s], self.ok[s], self.goal_next[s], self.k_q
        return [b[a] + ((kq if gn[a] else 0.0) if okr[a] else -kq) for a in range(8)]  # + k_q * r_q


# ---------------------------------------------------------------- the learner

def plan_map(grid: GridMap, config: QLearningConfig | None = None, warm_start: QLearningResult | None = None,
             **kw) -> QLearningResult:
    """:func:`plan` on a parsed map."""
    return plan(grid.occupancy, grid.start, grid.goal, config, warm_start, **kw)


def plan(occupancy: np.ndarray, start: Cell, goal: Cell, config: QLearningConfig | None = None,
         warm_start: QLearningResult | None = None, virtual: np.ndarray | None = None) -> QLearningResult:
    """Learn a path from ``start`` to ``goal`` on ``occupancy`` (``[x, y]``, True = obstacle).

    ``warm_start``: a previous result on a grid of the same shape and the same goal; its Q rows and
    virtual obstacles are reused except within one cell of a changed cell (otherwise: cold start).
    ``virtual``: virtual obstacles known beforehand (e.g. shared by another robot).
    """
    t0 = time.perf_counter()
    c = (config or QLearningConfig()).resolved()
    occupancy = np.asarray(occupancy, dtype=bool)
    check_cells(occupancy, start=start, goal=goal)
    u = _uniforms(np.random.default_rng(c.seed)).__next__
    keep, virtual = _warm_reuse(warm_start, occupancy, goal, virtual)
    world = GridWorld(occupancy, start, goal, c.corner_cutting, virtual)
    max_steps = c.max_steps or world.n_states
    Q, row_of = _initial_table(world, c, warm_start, keep)
    tr = _train(world, c, row_of, u, max_steps, t0)
    gpath, greached = _greedy_rollout(world, Q, max_steps)
    cell = world.cell
    return QLearningResult(
        variant=c.variant, seed=c.seed, converged=tr.converged_at is not None, convergence_round=tr.converged_at,
        convergence_time_s=tr.conv_time, rounds=tr.rounds, time_s=time.perf_counter() - t0,
        last_round_path=[cell(s_) for s_ in tr.path], reached=tr.reached,
        greedy_path=[cell(s_) for s_ in gpath], greedy_reached=greached,
        steps_per_round=tr.steps, reward_per_round=tr.rewards, epsilon_per_round=tr.epsilons,
        occupancy=occupancy.copy(), virtual=world.virtual.copy(), Q=_q_array(Q),
        start=(int(start[0]), int(start[1])), goal=(int(goal[0]), int(goal[1])), warm_started=keep is not None,
    )


def _warm_reuse(warm_start: QLearningResult | None, occupancy: np.ndarray, goal: Cell,
                virtual: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Replanning on a changed grid: the states whose Q rows a warm start keeps (None = cold start) and
    the virtual obstacles to start from. Rows and virtual obstacles within one cell of a change are dropped."""
    if warm_start is None or warm_start.occupancy.shape != occupancy.shape or tuple(warm_start.goal) != tuple(goal):
        return None, virtual
    changed = warm_start.occupancy != occupancy
    near = changed.copy()  # 3 x 3 dilation of the changed cells
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            near |= np.roll(np.roll(np.pad(changed, 1), dx, 0), dy, 1)[1:-1, 1:-1]
    keep = ~near.ravel() & ~np.isnan(warm_start.Q).any(axis=1)
    v0 = warm_start.virtual & ~near
    return keep, (v0 if virtual is None else (v0 | virtual))


def _initial_table(world: GridWorld, c: QLearningConfig, warm_start: QLearningResult | None,
                   keep: np.ndarray | None) -> tuple[list, Callable[[int], list[float]]]:
    """The Q-table as a list of rows (plain floats, fast in the loop; None = not initialised yet) and
    ``row_of(s)``, which initialises a row by eq. (9) the first time the robot stands on s (Q-L3..Q-L5)."""
    if c.gpf:
        init_row = GPFInit(world, c)
        Q: list = [None] * world.n_states
    else:
        init_row = None
        Q = [[0.0] * 8 for _ in range(world.n_states)]  # Algorithm 1: Q(s, a) = 0
    if keep is not None:
        Qw = warm_start.Q
        for s in np.flatnonzero(keep).tolist():
            Q[s] = Qw[s].tolist()

    def row_of(s: int) -> list[float]:
        r = Q[s]
        if r is None:
            r = Q[s] = init_row(s)
        return r

    return Q, row_of


@dataclass
class _Training:
    """What the rounds of :func:`_train` recorded."""

    steps: list[int] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    epsilons: list[float] = field(default_factory=list)
    reached_hist: list[bool] = field(default_factory=list)
    converged_at: int | None = None
    conv_time: float | None = None
    rounds: int = 0
    path: list[int] = field(default_factory=list)
    """States of the last round."""
    reached: bool = False
    """Whether the last round reached the goal."""


def _train(world: GridWorld, c: QLearningConfig, row_of, u, max_steps: int, t0: float) -> _Training:
    """Algorithms 1-2: rounds from the start until convergence (reading 5) or ``max_rounds``."""
    tr = _Training(path=[world.s_start])
    eps = c.epsilon
    W, lim = c.conv_rounds, c.conv_std ** 2
    for ep in range(c.max_rounds):
        tr.rounds = ep + 1
        row = row_of(world.s_start)
        if c.sa and ep % c.n == 0:  # Algorithm 2: "If episode % n == 0 Then ... update epsilon"
            T = c.T0 if ep == 0 else sa_temperature(tr.steps[-c.n:], c.i, c.k)  # eq. (10)
            a_rand = int(u() * 8)
            eps = sa_epsilon(row[a_rand], max(row), c.q, T)  # eq. (11)
        t, G, tr.reached, tr.path = _round(world, c, row_of, eps, u, max_steps)
        tr.steps.append(t)
        tr.rewards.append(G)
        tr.epsilons.append(eps)
        tr.reached_hist.append(tr.reached)
        if tr.converged_at is None and ep + 1 >= W and all(tr.reached_hist[-W:]):
            last = tr.steps[-W:]
            mu = sum(last) / W
            if sum((x - mu) ** 2 for x in last) / (W - 1) < lim:  # section 5.1: std of 10 rounds < 5
                tr.converged_at = ep + 1
                tr.conv_time = time.perf_counter() - t0
                if c.stop_at_convergence:
                    break
    return tr


def _round(world: GridWorld, c: QLearningConfig, row_of, eps: float, u, max_steps: int
           ) -> tuple[int, float, bool, list[int]]:
    """One round (episode) from the start: steps taken, return G, whether it reached the goal, its states."""
    nxt, ok = world.nxt, world.ok
    sg = world.s_goal
    r_goal, r_step, r_hit = REWARDS[c.reward]
    alpha, gamma = c.alpha, c.gamma
    terminal_hit = c.collision == "terminal"
    filling, fill_guard = c.filling, c.fill_guard
    s = world.s_start
    row = row_of(s)
    path = [s]
    G = 0.0
    t = 0
    while t < max_steps:
        if filling:  # Algorithm 2 step (3)
            _fill_if_trapped(world, s, fill_guard)
        # eq. (2): epsilon-greedy (delta < epsilon: random action), ties broken at random
        if u() < eps:
            a = int(u() * 8)
        else:
            m = max(row)
            if row.count(m) == 1:
                a = row.index(m)
            else:
                cand = [j for j in range(8) if row[j] == m]
                a = cand[int(u() * len(cand))]
        t += 1
        if ok[s][a]:
            s2 = nxt[s][a]
            if s2 == sg:
                row[a] += alpha * (r_goal - row[a])  # eq. (1) at the target: no max_a Q(s_t+1, a) term
                path.append(s2)
                return t, G + r_goal, True, path
            r = r_step
        else:
            r = r_hit
            if terminal_hit:
                row[a] += alpha * (r_hit - row[a])  # eq. (1), the round ends here
                return t, G + r_hit, False, path
            s2 = s
        row2 = row_of(s2)
        row[a] += alpha * (r + gamma * max(row2) - row[a])  # eq. (1)
        G += r
        s, row = s2, row2
        path.append(s)
    return t, G, False, path


def _fill_if_trapped(world: GridWorld, s: int, fill_guard: bool) -> None:
    """Algorithm 2 step (3): fill the current cell if every position nearer the goal is infeasible
    (with ``fill_guard``: unless that cuts the start off from the goal)."""
    cl = world.closer[s]
    if not cl or s in world.refused:
        return
    nx_s, blocked = world.nxt[s], world.blocked
    for a in cl:
        t_ = nx_s[a]
        if t_ >= 0 and not blocked[t_]:
            return
    world.fill(s)
    if fill_guard and not world.connected():
        world.unfill(s)
        world.refused.add(s)  # fills only add obstacles: this one would cut the start off again


def _greedy_rollout(world: GridWorld, Q: list, max_steps: int) -> tuple[list[int], bool]:
    """epsilon = 0 rollout of the final table on the final grid (reading 7): its states, whether it reached the goal."""
    nxt, ok, sg = world.nxt, world.ok, world.s_goal
    s = world.s_start
    gpath = [s]
    seen = {s}
    for _ in range(max_steps):
        r = Q[s]
        if r is None:
            break
        okr = ok[s]
        best = [r[j] if okr[j] else -math.inf for j in range(8)]  # the sensor vetoes blocked steps
        m = max(best)
        if m == -math.inf:
            break
        s = nxt[s][best.index(m)]
        gpath.append(s)
        if s == sg:
            return gpath, True
        if s in seen:
            break
        seen.add(s)
    return gpath, False


def _q_array(Q: list) -> np.ndarray:
    """The Q-table as an array (n_states, 8); rows never initialised are NaN."""
    Qa = np.full((len(Q), 8), np.nan)
    for s, r in enumerate(Q):
        if r is not None:
            Qa[s] = r
    return Qa


__all__ = ["VARIANTS", "FEATURES", "REWARDS", "QLearningConfig", "QLearningResult", "plan", "plan_map",
           "gpf", "gpf_q_init", "sa_temperature", "sa_epsilon", "STEP_LENGTH"]
