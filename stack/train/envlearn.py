"""A small learner on :class:`stack.train.env.FormationParallelEnv`: the example of docs/env.md.

Double DQN (Bai 2022 eq. (18)-(19), the update of :class:`stack.train.drl.Learner`) with every robot's
transitions in one replay memory (parameter sharing: one network drives every robot, as in the fleet),
epsilon-greedy over the 15 actions. What it saves is a ``DuelingQNet`` state_dict: the format
``--policy drl`` loads from ``robot.drl.weights``. Any other learner works the same way on the env;
this one is here to show the chain (env -> weights -> ``stack-agent``), not to beat the shipped weights:
a few thousand steps from scratch learn little, a few thousand from ``--init`` shipped weights keep them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stack.policies.drl.observation import BEAMS
from stack.train.env import FormationParallelEnv

KEYS = ("scans", "gv", "nb", "n_nb")


@dataclass
class EnvLearnConfig:
    """Settings of :func:`train_on_env` (unknown keys are errors: a dataclass)."""

    steps: int = 2000
    """environment steps (each gives one transition per live robot)"""
    init: str | Path | None = None
    """start from these weights (a DuelingQNet state_dict; None: a fresh network)"""
    seed: int = 0
    """seed of the env's scenes, the exploration and torch"""
    eps_start: float = 1.0
    """initial epsilon"""
    eps_end: float = 0.05
    """final epsilon (reached at 80 % of the steps)"""
    lr: float = 5e-4
    """Adam learning rate"""
    batch: int = 64
    """minibatch"""
    memory: int = 20_000
    """replay memory (transitions)"""
    learn_start: int = 200
    """transitions before the first update"""
    target_every: int = 100
    """gradient steps between target-network copies"""
    gamma: float = 0.99
    """discount"""
    threads: int = 1
    """torch threads"""


def batch_of(obs: dict, agents: list[str]) -> dict:
    """Per-agent network inputs -> one batch (arrays with a leading axis over ``agents``)."""
    return {k: np.stack([obs[a][k] for a in agents]) for k in KEYS}


def act(net, obs: dict, agents: list[str], eps: float, rng: np.random.Generator) -> dict:
    """Epsilon-greedy actions of ``net`` for ``agents``."""
    import torch

    from stack.train.drl import greedy

    if not agents:
        return {}
    a = greedy(net, batch_of(obs, agents), torch)
    explore = rng.random(len(agents)) < eps
    a = np.where(explore, rng.integers(0, 15, len(agents)), a)
    return {ag: int(x) for ag, x in zip(agents, a)}


def train_on_env(env: FormationParallelEnv, cfg: EnvLearnConfig, out: str | Path, log=print) -> dict:
    """Train on ``env`` for ``cfg.steps`` steps; write the state_dict to ``out``; return a summary."""
    import torch

    from stack.policies.drl.network import DuelingQNet
    from stack.policies.drl.policy import load_network
    from stack.train.drl import DrlJob, Learner, Replay

    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    net = load_network(cfg.init).train() if cfg.init else DuelingQNet()
    job = DrlJob(lr=cfg.lr, batch=cfg.batch, memory=cfg.memory, target_every=cfg.target_every, gamma=cfg.gamma,
                 learn_start=cfg.learn_start, eval_episodes=0, progress=False, plots=False)
    learner, memory = Learner(job, net), Replay(cfg.memory, BEAMS, env.k_nb, rng)
    obs, _ = env.reset(seed=cfg.seed)
    t0, episodes, returns, ret, losses = time.perf_counter(), 0, [], 0.0, []
    for step in range(cfg.steps):
        eps = cfg.eps_start + (cfg.eps_end - cfg.eps_start) * min(1.0, step / max(1.0, 0.8 * cfg.steps))
        live = list(env.agents)
        acts = act(net, obs, live, eps, rng)
        obs2, rew, term, _, _ = env.step(acts)
        memory.add(batch_of(obs, live), np.array([acts[a] for a in live]), np.array([rew[a] for a in live], np.float32),
                   batch_of(obs2, live), np.array([term[a] for a in live], np.float32), np.ones(len(live), np.float32))
        ret += sum(rew.values())
        obs = obs2
        if not env.agents:
            episodes, returns, ret = episodes + 1, returns + [ret], 0.0
            obs, _ = env.reset()
        if memory.n >= cfg.learn_start:
            losses.append(learner.update(memory.sample(cfg.batch)))
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), out)
    summary = {"steps": cfg.steps, "episodes": episodes, "updates": learner.steps,
               "mean_return": float(np.mean(returns)) if returns else None,
               "mean_loss_last_100": float(np.mean(losses[-100:])) if losses else None,
               "wall_s": round(time.perf_counter() - t0, 1), "weights": str(out)}
    log(f"trained {cfg.steps} steps ({episodes} episodes, {learner.steps} updates) in {summary['wall_s']} s -> {out}")
    return summary


def evaluate_on_env(net, env: FormationParallelEnv, episodes: int, seed: int) -> dict:
    """Greedy ``net`` on ``episodes`` episodes of ``env`` (seeds seed, seed+1, ...): the fractions of robots
    that arrived, collided and timed out (or stalled)."""
    rng = np.random.default_rng(seed)
    n = {"arrived": 0, "collided": 0, "timeout": 0}
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        while env.agents:
            live = list(env.agents)
            obs, _, term, trunc, info = env.step(act(net, obs, live, 0.0, rng))
            for a in live:
                if term[a] or trunc[a]:
                    k = "arrived" if info[a]["arrived"] else "collided" if info[a]["collided"] else "timeout"
                    n[k] += 1
    total = max(1, sum(n.values()))
    return {k: round(v / total, 4) for k, v in n.items()} | {"robots": total}
