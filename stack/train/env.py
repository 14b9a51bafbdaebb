"""A PettingZoo ``ParallelEnv`` (and a Gymnasium single-robot view) of the DRL training world.

The world is :class:`stack.train.drlworld.DrlWorld` (numpy, one environment): its motion, lidar,
collision and the reward of Bai 2022 eq. (14)-(17) (:mod:`stack.policies.drl.reward`). What each
robot observes is built the way the agent builds it, by the one builder:

  world state -> :func:`stack.models.observation.neighbour_view` + :func:`observation_fields`
             -> :class:`stack.policies.base.Observation`                 (what ``stack-agent`` hands a policy)
             -> :func:`network_inputs`: the drl normaliser of ``stack/policies/drl/observation.py``
                (eq. (11)-(13): o_z, [o_g, o_v], o_r), what ``DrlPolicy`` feeds its network.

Agents are ``robot_<id>``; the action is an index into the 15 actions of section III-B 2)
(:data:`stack.policies.drl.observation.ACTIONS`), so a policy trained here loads into ``stack-agent``
unchanged (a ``DuelingQNet`` state_dict: ``robot.drl.weights``). Scenes: a scenario or course file
read by :mod:`stack.scenario` (obstacles; each follower's target its final slot around the goal,
eq. (3), as in the training world's stage 2), or the training world's random scenes.

``env.robot_observation(agent)`` is the Observation itself (what any ``stack-agent`` policy's ``act``
takes). An agent terminates when it arrives (eq. 15), collides (eq. 6-8) or, with ``stall_steps``, stalls; it
is truncated at ``max_steps``. A stopped robot stays where it is, an obstacle to the others.
numpy, pettingzoo and gymnasium only (no torch, no pybullet).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from stack.models.geometry import slot_position
from stack.models.observation import neighbour_view, observation_fields
from stack.policies.base import Observation
from stack.policies.drl.observation import ACTIONS, BEAMS, D_COM, N_SCANS, goal_features, neighbour_features, scan_features
from stack.scenario import Scenario, load_scenario
from stack.train.drlworld import DrlWorld, WorldConfig, scene_arrays

__all__ = ["STAND", "EnvConfig", "FormationEnv", "FormationParallelEnv", "network_inputs", "scenario_scene"]

STAND = 2  #: the action index of (v, w) = (0, 0)


@dataclass
class EnvConfig:
    """Settings of :class:`FormationParallelEnv` (unknown keys are errors: a dataclass)."""

    scenario: str | Path | Scenario | None = None
    """A scenario or course file (or a parsed Scenario) to play; None: the training world's random scenes."""
    robots: int = 4
    """Random scenes: robots per scene (1: stage 1, one robot; 2..8: stage 2). Ignored with a scenario."""
    max_steps: int | None = None
    """Steps before truncation (None: the scenario's ``success.max_time`` / ``duration``, or 500 (Table I))."""
    noise_std: float | None = None
    """Lidar range noise [m] (None: the scenario's ``lidar.noise_std``, or 0.01 with random scenes)."""
    max_walls: int = 2
    """Random scenes: walls per scene, 0..max_walls (0: the paper's scattered cuboids and cylinders)."""
    time_penalty: float = 0.0
    """Subtracted from each step's reward until arrival (0: eq. (14) exactly; see reward.py)."""
    stall_steps: int = 0
    """A robot that moved < 0.1 m in this many steps terminates with -1 (0: off, the paper's episodes)."""


def scenario_scene(sc: Scenario) -> tuple:
    """A scenario as one training-world scene: (starts (R, 2), yaws (R,), goals (R, 2), circles, boxes).

    Targets: the leader's goal, each follower's final slot around it (eq. 3), a peer's own goal."""
    starts = np.array([r.pose[:2] for r in sc.robots], float)
    yaws = np.array([r.pose[2] for r in sc.robots], float)
    f = sc.formation
    goals = []
    for r in sc.robots:
        if f is None:
            goals.append(r.goal if r.goal is not None else r.pose[:2])
        elif r.id == f.leader:
            goals.append(f.goal)
        else:
            goals.append(slot_position(f.goal, f.final_slots[r.id]))
    n_c = sum(o.type == "cylinder" for o in sc.obstacles)
    circles, boxes = scene_arrays(sc.obstacles, max(n_c, 10), max(len(sc.obstacles) - n_c, 9))
    return starts, yaws, np.array(goals, float), circles, boxes


def _world_config(cfg: EnvConfig, sc: Scenario | None) -> WorldConfig:
    if sc is None:
        steps = cfg.max_steps or 500
        return WorldConfig(noise_std=0.01 if cfg.noise_std is None else cfg.noise_std, max_steps=steps,
                           robots=max(cfg.robots, 2), max_walls=cfg.max_walls, time_penalty=cfg.time_penalty,
                           stall_steps=cfg.stall_steps)
    r = sc.robots[0]  # the training world has one robot model: the first robot's
    limit = sc.success.max_time or sc.duration
    n_c = sum(o.type == "cylinder" for o in sc.obstacles)
    return WorldConfig(radius=r.radius, beams=r.lidar.beams, fov=r.lidar.fov, scan_range=r.lidar.range,
                       noise_std=r.lidar.noise_std if cfg.noise_std is None else cfg.noise_std, dt=sc.dt,
                       max_steps=cfg.max_steps or int(round(limit / sc.dt)), track=r.base.track,
                       wheel_radius=r.base.wheel_radius, wheel_accel=r.base.wheel_accel, max_circles=max(n_c, 10),
                       max_boxes=max(len(sc.obstacles) - n_c, 9), robots=max(len(sc.robots), 2),
                       time_penalty=cfg.time_penalty, stall_steps=cfg.stall_steps)


def network_inputs(obs: Observation, k_nb: int) -> dict:
    """An Observation -> the drl network's inputs as numpy (what ``DrlPolicy``'s ``encode`` makes of it):
    scans (3, 180) o_z, gv (4,) [o_g, o_v] (eq. 11-12), nb (k_nb, 2) o_r (eq. 13) right-padded, n_nb its count."""
    nb = neighbour_features(obs.neighbours)[:k_nb]
    pad = np.zeros((k_nb, 2), np.float32)
    pad[: len(nb)] = nb
    return {"scans": scan_features(obs.scans), "gv": goal_features(obs.d_g, obs.alpha_g, obs.v, obs.w),
            "nb": pad, "n_nb": np.int64(len(nb))}


def observation_space(k_nb: int) -> spaces.Dict:
    """The space of :func:`network_inputs` (o_g in [0, 1], bearings / pi and o_v in [-1, 1])."""
    low_gv = np.array([0.0, -1.0, -1.0, -1.0], np.float32)
    return spaces.Dict({"scans": spaces.Box(0.0, 1.0, (N_SCANS, BEAMS), np.float32),
                        "gv": spaces.Box(low_gv, np.ones(4, np.float32), dtype=np.float32),
                        "nb": spaces.Box(np.tile([0.0, -1.0], (k_nb, 1)).astype(np.float32),
                                         np.ones((k_nb, 2), np.float32), dtype=np.float32),
                        "n_nb": spaces.Discrete(k_nb + 1)})


class FormationParallelEnv(ParallelEnv):
    """Every robot of one training-world scene, stepped together (see the module docstring)."""

    metadata = {"name": "formation_v0", "render_modes": []}

    def __init__(self, cfg: EnvConfig | None = None, **kw):
        """``cfg`` or its fields as keywords (``FormationParallelEnv(scenario="scenarios/x.yaml")``)."""
        self.cfg = cfg = cfg or EnvConfig(**kw)
        sc = cfg.scenario
        self.scenario = load_scenario(sc) if isinstance(sc, (str, Path)) else sc
        self.wcfg = _world_config(cfg, self.scenario)
        ids = self.scenario.ids if self.scenario else range(1 if cfg.robots == 1 else cfg.robots)
        self.possible_agents = [f"robot_{i}" for i in ids]
        self._index = {a: k for k, a in enumerate(self.possible_agents)}
        self.comm_range = self.scenario.robots[0].comm_range if self.scenario else D_COM
        self.k_nb = max(len(self.possible_agents) - 1, 1)
        self.agents: list[str] = []
        self.world: DrlWorld | None = None
        self.render_mode = None

    @functools.lru_cache(maxsize=None)  # noqa: B019 - one space object per agent, as PettingZoo asks
    def observation_space(self, agent: str) -> spaces.Dict:
        return observation_space(self.k_nb)

    @functools.lru_cache(maxsize=None)  # noqa: B019
    def action_space(self, agent: str) -> spaces.Discrete:
        return spaces.Discrete(len(ACTIONS))

    def reset(self, seed: int | None = None, options: dict | None = None):
        R = len(self.possible_agents)
        fresh = self.world is None or seed is not None
        if fresh:
            self.world = DrlWorld(1, 1 if R == 1 else 2, seed=0 if seed is None else seed, cfg=self.wcfg)
        scenes = [scenario_scene(self.scenario)] if self.scenario else None
        if scenes is not None or not fresh:  # a fresh world already holds a fresh random scene
            self.world.reset(np.ones(1, bool), scenes)
        self.agents = list(self.possible_agents)
        return {a: network_inputs(self.robot_observation(a), self.k_nb) for a in self.agents}, {a: {} for a in self.agents}

    def robot_observation(self, agent: str) -> Observation:
        """What the agent's decision layer would hand the policy: exact poses, an ideal radio (age 0)."""
        w, i, c = self.world, self._index[agent], self.wcfg
        x, y, yaw = float(w.x[0, i]), float(w.y[0, i]), float(w.yaw[0, i])
        reports = [(w.x[0, j], w.y[0, j], w.yaw[0, j], w.v[0, j], w.w[0, j], 0.0, None) for j in range(w.R) if j != i]
        view = neighbour_view((x, y), yaw, reports, self.comm_range)
        scans = w.scans[0, i].astype(float) * c.scan_range  # the world keeps them normalised by its range
        return Observation(**observation_fields(x, y, yaw, float(w.v[0, i]), float(w.w[0, i]),
                                                (float(w.gx[0, i]), float(w.gy[0, i])), view, scans=scans,
                                                scan_range=c.scan_range, dt=c.dt))

    def step(self, actions: dict):
        w = self.world
        a = np.full((1, w.R), STAND, np.int64)
        for agent, act in actions.items():
            if agent in self.agents:
                a[0, self._index[agent]] = int(act)
        r, arrived, collided, _, _ = w.step(a, ACTIONS)
        out_of_time = bool(w.t[0] >= self.wcfg.max_steps)
        obs, rew, term, trunc, info = {}, {}, {}, {}, {}
        for agent in self.agents:
            i = self._index[agent]
            obs[agent], rew[agent] = network_inputs(self.robot_observation(agent), self.k_nb), float(r[0, i])
            term[agent] = bool(arrived[0, i] or collided[0, i] or w.stalled[0, i])
            trunc[agent] = out_of_time and not term[agent]
            info[agent] = {"arrived": bool(arrived[0, i]), "collided": bool(collided[0, i]),
                           "stalled": bool(w.stalled[0, i])}
        self.agents = [ag for ag in self.agents if not (term[ag] or trunc[ag])]
        return obs, rew, term, trunc, info

    def render(self):
        return None

    def close(self):
        pass


class FormationEnv(gymnasium.Env):
    """A Gymnasium view of one robot of :class:`FormationParallelEnv`: ``robot`` is controlled, the others
    act by ``others`` (a function of their network inputs -> an action index; default: stand still).
    The episode ends when the controlled robot terminates or is truncated."""

    metadata = {"render_modes": []}

    def __init__(self, cfg: EnvConfig | None = None, *, robot: int = 0, others: Callable[[dict], int] | None = None,
                 **kw):
        self.env = FormationParallelEnv(cfg or EnvConfig(**kw))
        if not 0 <= robot < len(self.env.possible_agents):
            raise ValueError(f"robot: expected 0..{len(self.env.possible_agents) - 1}, got {robot}")
        self.me = self.env.possible_agents[robot]
        self.others = others or (lambda _obs: STAND)
        self.observation_space = self.env.observation_space(self.me)
        self.action_space = self.env.action_space(self.me)
        self._obs: dict = {}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._obs, infos = self.env.reset(seed=seed, options=options)
        return self._obs[self.me], infos[self.me]

    def step(self, action):
        acts = {a: (int(action) if a == self.me else self.others(self._obs[a])) for a in self.env.agents}
        obs, rew, term, trunc, info = self.env.step(acts)
        self._obs = {a: obs[a] for a in self.env.agents}
        return obs[self.me], rew[self.me], term[self.me], trunc[self.me], info[self.me]
