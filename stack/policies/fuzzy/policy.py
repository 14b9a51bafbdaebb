"""``--policy fuzzy`` / ``fuzzy-lstm``: Chang 2020's hierarchical controller as one robot's policy.

Per control step (Algorithm 1, for this robot only):
  1. L_1..L_8 from the newest scan (:func:`.rbc.sectors`);
  2. D_goal of this robot and of every neighbour it has heard, and the neighbours' speeds and ages;
  3. the decentralised MRC (:class:`.mrc.Coordinator`): alpha_i, v_r by eq. (1)-(2), beta_i and
     theta_adj by eq. (7)-(8) (FLC_SR for ``fuzzy``, the peephole LSTM for ``fuzzy-lstm``, none for
     ``coordinator="none"``: constant v0, theta_adj = theta_goal);
  4. the RBC (:class:`.rbc.RobotBehaviourController`): supervisor, left/right BF or TS -> theta_r;
  5. (v, w) = (v_r, theta_r / turn_time).

What each robot knows of the others (the agent's Observation):
- ``neighbour_states`` ((n, 6) rows [x, y, yaw, v, w, age], world frame): their broadcast states with
  exact speeds and ages;
- ``neighbour_d_goal``: each arrival-time peer's distance to its own goal (``State.d_goal``), which is
  what the paper's central MRC ranks (every robot's distance to its target).
Where a peer did not say its D_goal (an older sender), or with ``peer_goals = False``, its distance to
this robot's goal stands in (goals of an arrival-time task lie "a little apart around the target": an
error of at most the spread of the goals), or to ``FuzzyConfig.target`` when that names the common
target. Without ``neighbour_states`` (a bare Observation of [distance, bearing] pairs), positions are
reconstructed from this robot's pose and speeds estimated by nearest-neighbour tracking (gate
``track_gate``, smoothing ``track_smooth``), with ages 0.

Additions of ours (the paper's Webots robots could not hit what its simulator kept them from):
- in TS the speed is multiplied by max(``cos_floor``, cos theta_r) (a unicycle turns before it
  speeds off sideways); near the goal it is at most d_goal / ``t_brake``;
- a guard: an obstacle within ``guard`` of the robot's centre in L_2..L_7 caps v at ``v_guard``,
  and one within ``side_guard`` in L_1-L_2 (L_7-L_8) makes it steer away by ``side_push`` (robots converging
  on neighbouring goals touched side by side without it);
- at the goal (d_goal < ``arrive_tol``) the robot stops and stays (until pushed 1 m off);
- once a neighbour has arrived (standing still within ``arrived_radius`` of the target) the
  others drive straight at v_max: nothing left to wait for;
- the arrival detour: within ``detour_radius`` of its goal, a robot whose straight line to the goal
  passes within 2 radius + ``detour_margin`` of a standing neighbour steers along the tangent past
  it on the goal's side instead of boundary following round it (robots that came up on the wrong
  sides for their goals otherwise circled the arrived ones, 12 s and more).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from ...estimation.pose import wrap as _wrap
from ...settings import check, rule
from ..base import Observation, Policy
from .mrc import Coordinator, FlcSr, LstmMrc, LstmWeights, MrcConfig, PeerEstimate
from .rbc import BF_LEFT, BF_RIGHT, TS, BoundaryFollower, RbcConfig, RobotBehaviourController, SupervisorConfig, sectors
from .tsk import TSK

PARAMS_DIR = Path(__file__).resolve().parent / "params"
PARAMS_FILE = PARAMS_DIR / "chang2020.json"
COORDINATORS = ("flc", "lstm", "none")


@dataclass
class FuzzyConfig:
    """``robot.fuzzy`` (``--policy fuzzy`` and ``fuzzy-lstm``): the policy's settings; the fields of
    :class:`MrcConfig` and :class:`SupervisorConfig` sit beside these (``robot.fuzzy.v_min``)."""

    RULE = (">= 0",)

    coordinator: Literal["flc", "lstm", "none"] = "flc"
    """"flc" (FLC_SR), "lstm" (recurrent MRC) or "none" (each robot alone, the paper's "no MRC");
    ``--policy fuzzy-lstm`` is always "lstm"."""
    params: str | None = None
    """A JSON file of trained parameters (default: the shipped ``params/chang2020.json``)."""
    target: tuple[float, float] | None = None
    """The common target [m, world]; None: this robot's own goal stands in for it (see module doc)."""
    turn_time: float = field(default=1.0, metadata=rule("> 0"))
    """[s] steering angle -> yaw rate: w = theta_r / turn_time."""
    arrive_tol: float = 0.4
    """[m] at the goal: stop and stay."""
    t_brake: float = field(default=1.5, metadata=rule("> 0"))
    """[s] near the goal v <= d_goal / t_brake."""
    cos_floor: float = 0.2
    """TS: v_r times max(cos_floor, cos theta_r)."""
    guard: float = 0.65
    """[m] an obstacle this near (centre to hit point) in L2..L7 caps the speed ..."""
    v_guard: float = 0.1
    """[m/s] ... at this."""
    side_guard: float = 0.6
    """[m] something this near in L1-L2 (L7-L8), and nothing as near on the other side, ..."""
    side_push: float = 0.3
    """[rad] ... makes the robot steer at least this much away from it."""
    arrived_radius: float = 2.0
    """[m] a neighbour standing (speed < 0.05 m/s) this near the target has arrived."""
    track_gate: float = 1.0
    """[m] association gate for neighbour tracking (plus v_max dt)."""
    track_smooth: float = 0.3
    """Exponential smoothing weight of a new speed sample."""
    detour_radius: float = 3.0
    """[m] within this of its goal a robot passes a standing neighbour in its way along the tangent on the
    goal's side (ours; 0: off, boundary following as anywhere else)."""
    detour_slow: float = 0.3
    """[m/s] a neighbour slower than this (standing, or creeping up to its own goal) is passed by the detour."""
    detour_margin: float = 0.45
    """[m] the clearance the detour keeps beyond the two radii (beyond ``guard``, so the guard does not hold
    the robot at ``v_guard`` all the way round)."""
    peer_goals: bool = True
    """Rank by the distances the peers report to their own goals (``State.d_goal``), as the paper's central
    MRC knows them; False: each peer's distance to this robot's goal (or to ``target``)."""
    mrc: MrcConfig = field(default_factory=MrcConfig, metadata={"inline": True})
    """The coordinator's settings (eq. 1-2, 7-8)."""
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig, metadata={"inline": True})
    """The behaviour supervisor's settings (Fig. 5)."""

    def __post_init__(self):
        check(self)
        if self.params is not None and not Path(self.params).is_file():
            raise ValueError(f"params: no such file: {self.params}")


def hand_set_params() -> dict:
    """Hand-set parameters (before PSO): a 10-rule left BF controller, a 5-rule FLC_SR, a small LSTM.

    BF rules on (L5, L6, L7, L8) [m], consequent theta [rad, CCW]; a straight wall at d on the left
    reads (2.61 d, 1.41 d, 1.08 d, d)."""
    D = 10.0  # a width this large makes an input "don't care" in a rule
    bf_m = [[3.0, 1.4, 1.0, 0.8],     # parallel at 0.8 m: straight on
            [3.0, 1.4, 1.0, 0.55],    # too close: turn right
            [3.0, 1.4, 1.0, 1.1],     # a little far: turn left
            [3.0, 2.0, 1.8, 1.5],     # too far: turn left more
            [0.6, 1.0, 1.0, 1.0],     # wall ahead (inner corner): turn right hard
            [3.0, 0.6, 1.0, 1.0],     # front-left close: turn right
            [5.0, 5.0, 5.0, 5.0],     # wall lost (outer corner): turn left, radius ~0.8 m
            [3.0, 1.4, 0.6, 1.0],     # left-front close: turn right
            [5.0, 5.0, 5.0, 0.8],     # corner passing behind: turn left gently
            [5.0, 1.2, 0.9, 0.8]]     # ideal, open ahead: straight
    bf_s = [[D, D, 0.3, 0.15], [D, D, D, 0.12], [D, D, D, 0.15], [D, D, 0.4, 0.3], [0.4, D, D, D],
            [D, 0.25, D, D], [D, D, 0.8, 0.8], [D, D, 0.2, D], [D, D, 1.0, 0.3], [2.0, 0.3, 0.2, 0.15]]
    bf_a = [[0.0], [-0.8], [0.4], [0.8], [-1.5], [-1.2], [0.5], [-1.0], [0.5], [0.0]]
    # FLC_SR on (D1, Dn, v1, vn, dD) / (50 m, 50 m, 1 m/s, 1 m/s, 50 m) -> (alpha_1, alpha_n)
    sr_m = [[0.3, 0.6, 0.5, 0.5, 0.3],   # large gap: slow the nearest, speed up the farthest
            [0.2, 0.2, 0.5, 0.5, 0.0],   # no gap: keep speeds
            [0.2, 0.2, 0.2, 0.8, 0.0],   # no gap, nearest slow and farthest fast: hold
            [0.2, 0.2, 0.8, 0.2, 0.0],   # no gap, nearest fast and farthest slow: slow the nearest
            [0.1, 0.15, 0.5, 0.5, 0.05]]  # small gap close in: gentle
    sr_s = [[0.5, 0.5, 0.5, 0.5, 0.15], [0.5, 0.5, 0.25, 0.25, 0.04], [0.5, 0.5, 0.2, 0.2, 0.04],
            [0.5, 0.5, 0.2, 0.2, 0.04], [0.5, 0.5, 0.5, 0.5, 0.04]]
    sr_a = [[0.9, 1.1], [1.0, 1.0], [1.0, 1.0], [0.95, 1.03], [0.97, 1.03]]
    rng = np.random.default_rng(7)
    lstm = LstmWeights.from_vector(rng.normal(0, 0.3, LstmWeights.N_PARAMS))
    lstm.W[0, 0, 4] = -3.0  # cell 0 (-> alpha_1) driven down by Delta D
    lstm.W[0, 1, 4] = 3.0  # cell 1 (-> alpha_n) up
    return {"bf_left": TSK(bf_m, bf_s, bf_a).to_dict(), "flc_sr": TSK(sr_m, sr_s, sr_a).to_dict(),
            "lstm": lstm.to_dict(), "meta": {"source": "hand-set"}}


def load_params(path: str | Path | None = None) -> dict:
    """The shipped parameters (``params/chang2020.json``), or the hand-set ones where it lacks a part."""
    p = Path(path) if path else PARAMS_FILE
    out = hand_set_params()
    if p.exists():
        out.update(json.loads(p.read_text()))
    return out


class FuzzyPolicy(Policy):
    name = "fuzzy"
    hybrid = False  # Chang's RBC has its own avoidance: it drives in every situation

    def __init__(self, cfg: FuzzyConfig | None = None, params: dict | None = None, *, fov: float = math.pi,
                 range_max: float = 5.0, v_max: float = 1.0, radius: float = 0.3):
        self.cfg = cfg = cfg or FuzzyConfig()
        if cfg.coordinator not in COORDINATORS:
            raise ValueError(f"coordinator must be one of {COORDINATORS}, got {cfg.coordinator!r}")
        self.params = params = params or load_params()
        self.name = {"flc": "fuzzy", "lstm": "fuzzy-lstm", "none": "fuzzy-nomrc"}[cfg.coordinator]
        self.fov, self.range_max, self.v_max, self.radius = fov, range_max, v_max, radius
        bf = BoundaryFollower(TSK.from_dict(params["bf_left"]))
        self.rbc = RobotBehaviourController(bf, RbcConfig(turn_time=cfg.turn_time, supervisor=cfg.supervisor),
                                            fov=fov, range_max=range_max)
        core = None
        if cfg.coordinator == "flc":
            core = FlcSr(TSK.from_dict(params["flc_sr"]))
        elif cfg.coordinator == "lstm":
            core = LstmMrc(LstmWeights.from_dict(params["lstm"]))
        mcfg = cfg.mrc
        if mcfg.v_max > v_max:
            mcfg = replace(mcfg, v_max=v_max, v0=min(mcfg.v0, v_max))
        self.mrc = Coordinator(core, mcfg)
        self.reset()

    def reset(self) -> None:
        self.rbc.reset()
        self.mrc.reset()
        self.arrived = False
        self.tracks: list[tuple[float, float, float]] = []  # (x, y, v) of neighbours last step
        self.behaviour = TS
        self.last = None  # the last Coordination (for tests and the numpy world's logs)

    # -- neighbours -------------------------------------------------------------------------
    def _peers(self, obs: Observation, target: tuple[float, float]) -> list[PeerEstimate]:
        states = getattr(obs, "neighbour_states", None)  # see the module doc
        if states is not None and np.asarray(states).size:
            st = np.asarray(states, float).reshape(-1, 6)  # x, y, yaw, v, w, age
            dg = np.asarray(getattr(obs, "neighbour_d_goal", np.zeros(0)), float).ravel()
            if not self.cfg.peer_goals or dg.size != len(st):
                dg = np.full(len(st), np.nan)
            return [PeerEstimate(float(g) if math.isfinite(g) else math.hypot(x - target[0], y - target[1]), v, age)
                    for (x, y, _, v, _, age), g in zip(st, dg)]
        nb = np.asarray(obs.neighbours, float).reshape(-1, 2)
        pos = [(obs.x + d * math.cos(obs.yaw + b), obs.y + d * math.sin(obs.yaw + b)) for d, b in nb]
        gate = self.cfg.track_gate + self.v_max * obs.dt
        new_tracks, peers = [], []
        used: set[int] = set()
        for px, py in pos:
            best, bd = None, gate
            for k, (tx, ty, _) in enumerate(self.tracks):
                dd = math.hypot(px - tx, py - ty)
                if k not in used and dd < bd:
                    best, bd = k, dd
            if best is None:
                v = self.mrc.cfg.v0
            else:
                used.add(best)
                s = self.cfg.track_smooth
                v = (1 - s) * self.tracks[best][2] + s * bd / max(obs.dt, 1e-3)
            new_tracks.append((px, py, v))
            peers.append(PeerEstimate(math.hypot(px - target[0], py - target[1]), v, 0.0))
        self.tracks = new_tracks
        return peers

    def _detour(self, obs: Observation, d_g: float, theta_goal: float) -> float | None:
        """The heading [rad, robot frame] past the nearest standing neighbour that blocks the straight line
        to the goal, on the goal's side; None when nobody stands in the way (or the way past is blocked too)."""
        states = np.asarray(getattr(obs, "neighbour_states", np.zeros((0, 6))), float).reshape(-1, 6)
        clear = 2.0 * self.radius + self.cfg.detour_margin
        standing = []
        for x, y, _, v, _, _ in states:
            r = math.hypot(x - obs.x, y - obs.y)
            if abs(v) < self.cfg.detour_slow and r < d_g + self.radius:  # slow, and nearer than the goal
                b = _wrap(math.atan2(y - obs.y, x - obs.x) - obs.yaw)
                # the tangent's angle off its bearing; nearer than ``clear``, up to 45 deg more: away from it
                phi = math.asin(clear / r) if r > clear else math.pi / 2 + min(math.pi / 4, (clear - r) / clear * math.pi)
                standing.append((r, b, phi))
        heading = theta_goal
        for r, b, phi in sorted(standing):
            delta = _wrap(theta_goal - b)
            if abs(delta) < phi:  # the line to the goal passes within ``clear`` of it: by its tangent
                heading = _wrap(b + math.copysign(phi, delta if delta != 0.0 else 1.0))
                break
        else:
            return None
        for r, b, phi in standing:  # the tangent itself must be open: to the other robots ...
            if abs(_wrap(heading - b)) < phi - 1e-9:
                return None
        scan = np.asarray(obs.scans)[-1] if np.asarray(obs.scans).size else np.zeros(0)
        if scan.size:  # ... and to the lidar within 15 deg of it (where it looks that way: else turning shows it)
            ang = np.linspace(-self.fov / 2, self.fov / 2, scan.size)
            cone = np.abs(ang - heading) < math.radians(15.0)
            if cone.any() and scan[cone].min() < clear:
                return None
        return heading

    # -- the step ---------------------------------------------------------------------------
    def act(self, obs: Observation) -> tuple[float, float]:
        cfg = self.cfg
        d_g, theta_goal = float(obs.d_g), float(obs.alpha_g)
        if self.arrived and d_g > cfg.arrive_tol + 1.0:
            self.arrived = False
        if d_g < cfg.arrive_tol:
            self.arrived = True
        scan = obs.scans[-1] if np.asarray(obs.scans).size else np.zeros(0)
        L = sectors(scan, self.fov, obs.scan_range or self.range_max)
        own_goal = obs.target if obs.target is not None else (obs.x + d_g * math.cos(obs.yaw + theta_goal),
                                                               obs.y + d_g * math.sin(obs.yaw + theta_goal))
        common = cfg.target
        target = common or own_goal
        reported = np.asarray(getattr(obs, "neighbour_d_goal", np.zeros(0)), float)
        if cfg.peer_goals and reported.size and np.isfinite(reported).any():
            common = None  # the peers say how far each is from its own goal: so does this robot
        d_own = math.hypot(obs.x - target[0], obs.y - target[1]) if common else d_g
        peers = self._peers(obs, target)
        if self.arrived:
            self.behaviour = "arrived"
            return 0.0, 0.0
        someone_in = any(p.d_goal < cfg.arrived_radius and p.v < 0.05 for p in peers)
        co = self.mrc.step(d_own, [] if someone_in else peers)
        self.last = co
        v = self.mrc.cfg.v_max if (someone_in and cfg.coordinator != "none") else co.v
        theta_adj = self.mrc.theta_adj(theta_goal, co)
        detour = self._detour(obs, d_g, theta_goal) if d_g < cfg.detour_radius else None
        if detour is None:
            self.behaviour, theta_r = self.rbc.steer(L, d_g, theta_goal, theta_adj)
        else:  # past a standing robot toward the goal; target searching again once by it
            self.rbc.reset()
            self.behaviour, theta_r = TS, detour
        left_near, right_near = L[6:].min() < cfg.side_guard, L[:2].min() < cfg.side_guard
        if left_near != right_near:  # never turn into something beside the robot; ease away from it
            theta_r = min(theta_r, -cfg.side_push) if left_near else max(theta_r, cfg.side_push)
        if self.behaviour == TS:
            v *= max(cfg.cos_floor, math.cos(theta_r))
        v = min(v, max(0.05, d_g / cfg.t_brake))
        if L[1:7].min() < cfg.guard:
            v = min(v, cfg.v_guard)
        return float(v), float(theta_r / cfg.turn_time)


def make_fuzzy(robot=None, *, seed: int = 0, coordinator: str | None = None, params: str | Path | None = None,
               **_) -> FuzzyPolicy:
    """Factory: ``robot`` is a :class:`stack.scenario.RobotConfig` (None: defaults); its ``robot.fuzzy``
    (:class:`FuzzyConfig`) is the policy's config. ``coordinator`` (FLC_SR, the LSTM or none) and ``params``
    (a JSON file), when given, override the config's. ``seed`` is unused (the policy is deterministic)."""
    cfg = robot.config_for("fuzzy") if robot is not None else FuzzyConfig()
    if coordinator is not None:
        cfg = replace(cfg, coordinator=coordinator)
    table = load_params(params or cfg.params)
    if robot is None:
        return FuzzyPolicy(cfg, table)
    return FuzzyPolicy(cfg, table, fov=robot.lidar.fov, range_max=robot.lidar.range, v_max=robot.v_max,
                       radius=robot.radius)


def make_fuzzy_lstm(robot=None, **kw) -> FuzzyPolicy:
    kw["coordinator"] = "lstm"
    return make_fuzzy(robot, **kw)


__all__ = ["BF_LEFT", "BF_RIGHT", "TS", "FuzzyConfig", "FuzzyPolicy", "PARAMS_FILE", "hand_set_params",
           "load_params", "make_fuzzy", "make_fuzzy_lstm"]
