"""Bai 2022 section III-D / V-A: train the dueling double DQN (Algorithm 1), stage 1 or stage 2.

Examples:
  stack-train drl --stage 1 --out runs/drl-s1
  stack-train drl --stage 2 --init runs/drl-s1/drl.pt --out runs/drl-s2
  stack-train drl --evaluate stack/policies/drl/weights/drl.pt --stage 1

Stage 1: one robot among random obstacles; stage 2: four robots, one trained robot per episode
(chosen at random), the others greedy on a copy of its network refreshed every N transitions.
The world is :mod:`stack.train.drlworld` (numpy, many environments in parallel). Double DQN
target (eq. 18, Algorithm 1):

  y = r                                                       if the episode ends at the next step
  y = r + gamma Q^(o', argmax_a Q(o', a; theta); theta^-)     otherwise  (a timeout bootstraps)

Writes OUT/drl.pt (state_dict, the policy's format), OUT/best.pt (best 50-episode mean reward
once epsilon is at its floor), OUT/drl.json (the settings, the per-episode curve, the held-out
evaluation) and OUT/reward.png (the 50-episode mean reward, like Fig. 8); checkpoints of drl.pt
every few minutes. The weights the policy ships are OUT/drl.pt (or best.pt) copied to
stack/policies/drl/weights/drl.pt with OUT/drl.json beside it.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..argtypes import nonnegative_float, nonnegative_int, positive_int
from . import InputError

HELD_OUT_SEED = 20261


@dataclass
class DrlJob:
    """What ``stack-train drl`` runs; defaults are Table I where our setting can follow it."""

    stage: int = 1
    out: Path = Path("runs/drl")
    episodes: int = 5000  # section V-A: max-episodes 5000 (stage 1), 10000 (stage 2)
    envs: int = 16  # environments stepped together (the paper: one gazebo world)
    batch: int = 128  # Table I: 32
    memory: int = 100_000  # Table I: 2000
    gamma: float = 0.99  # Table I
    lr: float = 1e-3  # Table I (Adam)
    target_every: int = 500  # Table I C, in gradient steps
    copy_every: int = 10_000  # Table I N, in trained-robot transitions (stage 2)
    eps_start: float | None = None  # None: 1.0 (stage 1), 0.5 (stage 2)
    eps_end: float = 0.1
    eps_fraction: float | None = None  # of the episodes over which epsilon falls: 3000/5000, 7000/10000
    learn_start: int = 1000  # transitions before the first update
    updates_per_step: int = 1  # gradient steps per parallel step (of ``envs`` transitions)
    n_step: int = 1  # n-step returns (1: eq. 18 as printed)
    huber: bool = True  # Huber instead of the squared TD error of Algorithm 1
    grad_clip: float = 10.0
    max_steps: int = 500  # Table I max-step
    time_penalty: float = 0.0  # ours: reward per step that does not arrive is lowered by this (0: eq. 14-17)
    stall_steps: int = 0  # ours: standing (moving < 0.1 m) this many steps ends the episode with -1 (0: off)
    robots: int = 4  # stage 2: robots per scene (the paper: four)
    max_walls: int = 2  # walls across the way per scene, 0..max_walls (0: the paper's cuboids and cylinders)
    seed: int = 0
    init: Path | None = None
    max_minutes: float | None = None
    stop_after: int | None = None  # stop after this many episodes (the epsilon schedule still spans ``episodes``)
    checkpoint_minutes: float = 3.0
    eval_episodes: int = 200
    threads: int = 1
    progress: bool = True
    plots: bool = True
    extra: dict = field(default_factory=dict)

    def epsilon(self, episode: int) -> float:
        e0 = self.eps_start if self.eps_start is not None else (1.0 if self.stage == 1 else 0.5)
        frac = self.eps_fraction if self.eps_fraction is not None else (0.6 if self.stage == 1 else 0.7)
        k = min(1.0, episode / max(1.0, frac * self.episodes))
        return e0 + (self.eps_end - e0) * k


# --- batches of observations ---------------------------------------------------------------------
def pick(obs: dict, rows: np.ndarray, cols: np.ndarray) -> dict:
    """The observations of robots (rows[k], cols[k]) of :meth:`DrlWorld.observe`."""
    return {k: v[rows, cols] for k, v in obs.items()}


def tensors(o: dict, torch):
    nb = torch.from_numpy(np.ascontiguousarray(o["nb"], np.float32))
    return (torch.from_numpy(np.ascontiguousarray(o["scans"], np.float32)), torch.from_numpy(np.ascontiguousarray(o["gv"])),
            nb, torch.from_numpy(np.ascontiguousarray(o["n_nb"])))


class Replay:
    """Replay memory D of Algorithm 1 (scans stored as uint8, 2 cm steps over 5 m)."""

    def __init__(self, size: int, beams: int, k_nb: int, rng: np.random.Generator):
        self.size, self.n, self.i, self.rng = size, 0, 0, rng
        self.o = self._alloc(size, beams, k_nb)
        self.o2 = self._alloc(size, beams, k_nb)
        self.a = np.zeros(size, np.int64)
        self.r = np.zeros(size, np.float32)
        self.term = np.zeros(size, np.float32)
        self.disc = np.ones(size, np.float32)  # gamma^k of the bootstrap (k = the transition's steps)

    @staticmethod
    def _alloc(size, beams, k):
        return {"scans": np.zeros((size, 3, beams), np.uint8), "gv": np.zeros((size, 4), np.float32),
                "nb": np.zeros((size, k, 2), np.float32), "n_nb": np.zeros(size, np.int64)}

    def add(self, o, a, r, o2, term, disc) -> None:
        m = len(a)
        idx = (self.i + np.arange(m)) % self.size
        for dst, src in ((self.o, o), (self.o2, o2)):
            dst["scans"][idx] = np.round(src["scans"] * 255)
            for k in ("gv", "nb", "n_nb"):
                dst[k][idx] = src[k]
        self.a[idx], self.r[idx], self.term[idx], self.disc[idx] = a, r, term, disc
        self.i = (self.i + m) % self.size
        self.n = min(self.size, self.n + m)

    def get(self, idx) -> tuple:
        def view(d):
            return {"scans": d["scans"][idx].astype(np.float32) / 255, "gv": d["gv"][idx], "nb": d["nb"][idx], "n_nb": d["n_nb"][idx]}

        return view(self.o), self.a[idx], self.r[idx], view(self.o2), self.term[idx], self.disc[idx]

    def sample(self, batch: int):
        return self.get(self.rng.integers(0, self.n, batch))


class Learner:
    """Q (theta), Q^ (theta^-) and Adam: the double DQN update of eq. (18)-(19)."""

    def __init__(self, job: DrlJob, net=None):
        import torch

        from stack.policies.drl.network import DuelingQNet

        self.torch, self.job = torch, job
        self.q = net if net is not None else DuelingQNet()
        self.q_target = DuelingQNet()
        self.q_target.load_state_dict(self.q.state_dict())
        self.opt = torch.optim.Adam(self.q.parameters(), lr=job.lr)
        self.steps = 0

    def td_error(self, o, a, r, o2, term, disc=None):
        torch = self.torch
        q = self.q(*tensors(o, torch)).gather(1, torch.from_numpy(a)[:, None])[:, 0]
        with torch.no_grad():
            x2 = tensors(o2, torch)
            a_star = self.q(*x2).argmax(1, keepdim=True)  # select with theta
            q_next = self.q_target(*x2).gather(1, a_star)[:, 0]  # evaluate with theta^-
            g = self.job.gamma * (torch.ones_like(q_next) if disc is None else torch.from_numpy(disc))  # gamma^n (n-step)
            y = torch.from_numpy(r) + g * (1.0 - torch.from_numpy(term)) * q_next  # eq. (18)
        return q - y

    def loss(self, batch):
        e = self.td_error(*batch)
        if self.job.huber:
            return self.torch.nn.functional.smooth_l1_loss(e, self.torch.zeros_like(e))
        return (e ** 2).mean()

    def update(self, batch) -> float:
        loss = self.loss(batch)
        self.opt.zero_grad()
        loss.backward()
        self.torch.nn.utils.clip_grad_norm_(self.q.parameters(), self.job.grad_clip)
        self.opt.step()  # eq. (19), by Adam
        self.steps += 1
        if self.steps % self.job.target_every == 0:
            self.q_target.load_state_dict(self.q.state_dict())  # every C steps theta^- = theta
        return float(loss.detach())


def greedy(net, o: dict, torch) -> np.ndarray:
    if len(o["gv"]) == 0:
        return np.zeros(0, np.int64)
    with torch.no_grad():
        return net(*tensors(o, torch)).argmax(1).numpy()


class NStep:
    """n-step transitions (o_t, a_t, sum_k gamma^k r_t+k, o_t+n) per environment into the replay memory."""

    def __init__(self, D: Replay, n: int, gamma: float, envs: int):
        self.D, self.n, self.gamma = D, n, gamma
        self.pending: list[list] = [[] for _ in range(envs)]

    def push(self, o, a, r, o2, term, done) -> None:
        if self.n == 1:
            self.D.add(o, a, r, o2, term, self.gamma)
            return
        rows, out = [], []
        for e in range(len(a)):
            p = self.pending[e]
            p.append(({k: v[e] for k, v in o.items()}, a[e], r[e]))
            while p and (len(p) == self.n or done[e]):
                ret = sum(self.gamma ** k * x[2] for k, x in enumerate(p))
                out.append((p[0][0], p[0][1], ret, self.gamma ** len(p), term[e]))
                rows.append(e)
                p.pop(0)
        if rows:
            rows = np.array(rows)
            first = {k: np.stack([t[0][k] for t in out]) for k in o}
            self.D.add(first, np.array([t[1] for t in out]), np.array([t[2] for t in out], np.float32),
                       {k: v[rows] for k, v in o2.items()}, np.array([t[4] for t in out], np.float32),
                       np.array([t[3] for t in out], np.float32))


# --- evaluation ------------------------------------------------------------------------------------
def evaluate(net, *, stage: int = 1, episodes: int = 200, seed: int = HELD_OUT_SEED, max_steps: int = 500,
             epsilon: float = 0.0, max_walls: int = 2, robots: int = 4) -> dict:
    """Greedy run of ``net`` on the held-out scenes: success / collision / timeout rates.

    Stage 1: one robot per scene. Stage 2: all four robots drive with ``net``; a scene succeeds
    when every robot arrives, fails by collision when any collides. ``epsilon``: the chance of a
    random action per step (the policy's ``explore``; 0: greedy)."""
    import torch

    from stack.policies.drl.observation import ACTIONS

    from .drlworld import DrlWorld, WorldConfig, held_out_scenes

    scenes = held_out_scenes(episodes, stage, seed, max_walls, robots)
    w = DrlWorld(episodes, stage, seed=seed + 1, cfg=WorldConfig(max_steps=max_steps, max_walls=max_walls, robots=robots))
    w.reset(np.ones(episodes, bool), scenes)
    arrived = np.zeros((episodes, w.R), bool)
    collided = np.zeros((episodes, w.R), bool)
    steps = np.zeros(episodes, int)
    net.eval()
    for t in range(max_steps):
        live = w.active.any(axis=1)
        if not live.any():
            break
        o = w.observe()
        a = greedy(net, {k: v.reshape((episodes * w.R,) + v.shape[2:]) for k, v in o.items()}, torch).reshape(episodes, w.R)
        if epsilon > 0:
            rand = w.rng.random(a.shape) < epsilon
            a[rand] = w.rng.integers(0, len(ACTIONS), rand.sum())
        _, arr, col, _, _ = w.step(a, ACTIONS)
        arrived |= arr
        collided |= col
        steps[live] = t + 1
    succ = arrived.all(axis=1) & ~collided.any(axis=1)
    coll = collided.any(axis=1)
    return {"episodes": episodes, "stage": stage, "seed": seed, "epsilon": epsilon, "max_walls": max_walls, "robots": w.R, "success": float(succ.mean()), "collision": float(coll.mean()),
            "timeout": float((~succ & ~coll).mean()), "mean_steps_success": float(steps[succ].mean()) if succ.any() else None}


# --- training ----------------------------------------------------------------------------------------
def train(job: DrlJob, log=print) -> dict:
    import torch

    from stack.policies.drl.network import DuelingQNet
    from stack.policies.drl.observation import ACTIONS, N_ACTIONS

    from .drlworld import DrlWorld, WorldConfig

    torch.set_num_threads(job.threads)
    torch.manual_seed(job.seed)
    rng = np.random.default_rng(job.seed)
    job.out.mkdir(parents=True, exist_ok=True)
    net = DuelingQNet()
    if job.init:
        net.load_state_dict(torch.load(job.init, map_location="cpu", weights_only=True))
    L = Learner(job, net)
    frozen = DuelingQNet()  # theta~ of the other robots (stage 2)
    frozen.load_state_dict(net.state_dict())
    world = DrlWorld(job.envs, job.stage, seed=job.seed, cfg=WorldConfig(max_steps=job.max_steps, time_penalty=job.time_penalty,
                                                                 stall_steps=job.stall_steps, max_walls=job.max_walls,
                                                                 robots=job.robots))
    N, R = world.N, world.R
    D = Replay(job.memory, world.cfg.beams, R - 1, rng)
    rows = np.arange(N)
    ep_return = np.zeros(N)
    curve: list[dict] = []
    losses: list[float] = []
    best, since_copy, steps, episode = -math.inf, 0, 0, 0
    t0 = last_ckpt = time.monotonic()
    bar = None
    if job.progress:
        from tqdm import tqdm

        bar = tqdm(total=job.episodes, desc=f"drl stage {job.stage}", unit="ep", dynamic_ncols=True, mininterval=2.0)

    def save(path: Path) -> None:
        torch.save(L.q.state_dict(), path)

    nstep = NStep(D, job.n_step, job.gamma, N)
    obs = world.observe()
    while episode < job.episodes:
        if job.max_minutes and time.monotonic() - t0 > 60 * job.max_minutes:
            log(f"time limit: {job.max_minutes} min reached after {episode} episodes")
            break
        if job.stop_after and episode >= job.stop_after:
            break
        eps = job.epsilon(episode)
        tr = world.trained
        o = pick(obs, rows, tr)
        a_tr = greedy(L.q, o, torch)
        explore = rng.random(N) < eps
        a_tr[explore] = rng.integers(0, N_ACTIONS, explore.sum())
        actions = np.zeros((N, R), np.int64)
        if R > 1:
            others = np.ones((N, R), bool)
            others[rows, tr] = False
            rr, cc = np.nonzero(others)
            actions[rr, cc] = greedy(frozen, pick(obs, rr, cc), torch)
        actions[rows, tr] = a_tr
        r, arrived, collided, done, timeout = world.step(actions, ACTIONS)
        obs2 = world.observe()
        term = (arrived[rows, tr] | collided[rows, tr] | world.stalled[rows, tr]).astype(np.float32)
        o2 = pick(obs2, rows, tr)
        nstep.push(o, a_tr, r[rows, tr], o2, term, done)
        ep_return += r[rows, tr]
        steps += N
        since_copy += N
        for n in np.nonzero(done)[0]:
            episode += 1
            outcome = ("arrived" if arrived[n, tr[n]] else "collided" if collided[n, tr[n]]
                       else "stalled" if world.stalled[n, tr[n]] else "timeout")
            curve.append({"episode": episode, "return": round(float(ep_return[n]), 3), "outcome": outcome,
                          "steps": int(world.t[n]), "epsilon": round(eps, 4)})
        if done.any():
            ep_return[done] = 0.0
            world.reset(done)
            obs2 = world.observe()
        obs = obs2
        if D.n >= max(job.learn_start, job.batch):
            for _ in range(job.updates_per_step):
                losses.append(L.update(D.sample(job.batch)))
        if R > 1 and since_copy >= job.copy_every:
            frozen.load_state_dict(L.q.state_dict())  # every N steps theta~ = theta
            since_copy = 0
        if curve and done.any():
            recent = curve[-50:]
            mean50 = float(np.mean([c["return"] for c in recent]))
            if len(curve) >= 50 and eps <= job.eps_end + 1e-9 and mean50 > best:
                best = mean50
                save(job.out / "best.pt")
            if bar is not None:
                bar.n = min(episode, job.episodes)
                succ = np.mean([c["outcome"] == "arrived" for c in recent])
                bar.set_postfix(eps=f"{eps:.2f}", reward50=f"{mean50:.2f}", success50=f"{succ:.2f}",
                                loss=f"{np.mean(losses[-100:]) if losses else 0:.3f}",
                                steps_s=f"{steps / (time.monotonic() - t0):.0f}", refresh=False)
                bar.update(0)
        if time.monotonic() - last_ckpt > 60 * job.checkpoint_minutes:
            save(job.out / "drl.pt")
            _write_json(job, curve, losses, steps, time.monotonic() - t0, None)
            last_ckpt = time.monotonic()
    if bar is not None:
        bar.close()
    wall = time.monotonic() - t0
    save(job.out / "drl.pt")
    log(f"{episode} episodes, {steps} env steps in {wall:.0f} s ({steps / wall:.0f} env steps/s), {L.steps} gradient steps")
    ev = None
    if job.eval_episodes:
        ev = {"drl.pt": evaluate(L.q, stage=job.stage, episodes=job.eval_episodes, max_steps=job.max_steps, max_walls=job.max_walls, robots=job.robots)}
        if (job.out / "best.pt").exists():
            b = DuelingQNet()
            b.load_state_dict(torch.load(job.out / "best.pt", weights_only=True))
            ev["best.pt"] = evaluate(b, stage=job.stage, episodes=job.eval_episodes, max_steps=job.max_steps, max_walls=job.max_walls, robots=job.robots)
        for k, v in ev.items():
            log(f"held-out {k}: success {v['success']:.3f}, collision {v['collision']:.3f}, timeout {v['timeout']:.3f}")
    summary = _write_json(job, curve, losses, steps, wall, ev)
    if job.plots:
        _plot(curve, job.out / "reward.png", job.stage)
    return summary


def _write_json(job, curve, losses, steps, wall, ev) -> dict:
    d = {"paper": "Bai 2022, Algorithm 1", "job": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(job).items()},
         "episodes": len(curve), "env_steps": steps, "gradient_steps": len(losses), "wall_s": round(wall, 1),
         "env_steps_per_s": round(steps / max(wall, 1e-9), 1),
         "loss_first_100": float(np.mean(losses[:100])) if losses else None, "loss_last_100": float(np.mean(losses[-100:])) if losses else None,
         "evaluation": ev, "curve": curve}
    (job.out / "drl.json").write_text(json.dumps(d, indent=1))
    return d


def _plot(curve, path: Path, stage: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not curve:
        return
    ret = np.array([c["return"] for c in curve])
    k = np.arange(len(ret)) // 50
    means = np.bincount(k, ret) / np.bincount(k)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot((np.arange(len(means)) + 1) * 50, means)
    ax.set_xlabel("episode")
    ax.set_ylabel("average reward (50 episodes)")
    ax.set_title(f"stage {stage} (Bai 2022 Fig. 8)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --- command line ----------------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    j = DrlJob()
    p.add_argument("--stage", type=int, choices=(1, 2), default=1, help="curriculum stage (default 1)")
    p.add_argument("--out", type=Path, default=Path("runs/drl"), help="output folder (default runs/drl)")
    p.add_argument("--init", type=Path, help="start from these weights (stage 2: the stage-1 drl.pt)")
    p.add_argument("--episodes", type=positive_int, help="max-episodes (default 5000 stage 1, 10000 stage 2)")
    p.add_argument("--envs", type=positive_int, default=j.envs, help=f"parallel environments (default {j.envs})")
    p.add_argument("--batch", type=positive_int, default=j.batch, help=f"minibatch (default {j.batch}; Table I: 32)")
    p.add_argument("--memory", type=positive_int, default=j.memory, help=f"replay memory (default {j.memory}; Table I: 2000)")
    p.add_argument("--lr", type=float, default=j.lr, help=f"Adam learning rate (default {j.lr:g})")
    p.add_argument("--gamma", type=float, default=j.gamma, help=f"discount (default {j.gamma:g})")
    p.add_argument("--target-every", type=positive_int, default=j.target_every, help="C, gradient steps (default 500)")
    p.add_argument("--copy-every", type=positive_int, default=j.copy_every, help="N, transitions (stage 2, default 10000)")
    p.add_argument("--eps-start", type=float, help="default 1.0 (stage 1), 0.5 (stage 2)")
    p.add_argument("--eps-end", type=float, default=j.eps_end, help="default 0.1")
    p.add_argument("--eps-fraction", type=float, help="fraction of the episodes over which epsilon falls (default 0.6 / 0.7)")
    p.add_argument("--updates-per-step", type=positive_int, default=j.updates_per_step, help="gradient steps per parallel step")
    p.add_argument("--n-step", type=positive_int, default=1, help="n-step returns (default 1: eq. 18)")
    p.add_argument("--mse", action="store_true", help="squared TD error (Algorithm 1) instead of Huber")
    p.add_argument("--max-steps", type=positive_int, default=j.max_steps, help="max-step per episode (default 500)")
    p.add_argument("--time-penalty", type=nonnegative_float, default=0.0,
                   help="subtract this from every step's reward until arrival (default 0: eq. 14-17 as printed)")
    p.add_argument("--stall-steps", type=nonnegative_int, default=0,
                   help="end an episode with -1 when the robot has moved < 0.1 m in this many steps (default 0: off)")
    p.add_argument("--walls", type=int, choices=range(0, 4), default=2, metavar="N",
                   help="walls (2-10 m, across the way) per training / held-out scene, 0..N (default 2; 0: the paper's "
                        "randomly scattered cuboids and cylinders)")
    p.add_argument("--robots", type=int, choices=range(2, 9), default=4, metavar="N",
                   help="stage 2: robots per scene, 2..8 (default 4, the paper's)")
    p.add_argument("--max-minutes", type=float, help="stop (and save, and evaluate) after this wall time")
    p.add_argument("--stop-after", type=positive_int, metavar="EPISODES",
                   help="stop after this many episodes (the epsilon schedule still spans --episodes): replays a run cut by --max-minutes")
    p.add_argument("--checkpoint-minutes", type=float, default=j.checkpoint_minutes, help="write drl.pt this often")
    p.add_argument("--eval-episodes", type=int, default=j.eval_episodes, help="held-out episodes at the end (0: none)")
    p.add_argument("--evaluate", type=Path, metavar="WEIGHTS", help="only evaluate these weights on the held-out scenes")
    p.add_argument("--eval-seed", type=int, default=HELD_OUT_SEED,
                   help=f"the held-out scenes' seed (default {HELD_OUT_SEED}; another one: a fresh set nobody chose weights on)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--no-progress", action="store_true")


def main(args: argparse.Namespace) -> int:
    import torch

    from stack.policies.drl.network import DuelingQNet

    if args.evaluate:
        if not args.evaluate.exists():
            raise InputError(f"{args.evaluate}: no such weights file")
        torch.set_num_threads(args.threads)
        net = DuelingQNet()
        net.load_state_dict(torch.load(args.evaluate, map_location="cpu", weights_only=True))
        print(json.dumps(evaluate(net, stage=args.stage, episodes=args.eval_episodes or 200, max_steps=args.max_steps,
                                         max_walls=args.walls, robots=args.robots, seed=args.eval_seed)))
        return 0
    if args.init is not None and not args.init.exists():
        raise InputError(f"{args.init}: no such weights file")
    job = DrlJob(stage=args.stage, out=args.out, init=args.init, episodes=args.episodes or (5000 if args.stage == 1 else 10000),
                 envs=args.envs, batch=args.batch, memory=args.memory, lr=args.lr, gamma=args.gamma, target_every=args.target_every,
                 copy_every=args.copy_every, eps_start=args.eps_start, eps_end=args.eps_end, eps_fraction=args.eps_fraction,
                 updates_per_step=args.updates_per_step, n_step=args.n_step, huber=not args.mse, max_steps=args.max_steps, time_penalty=args.time_penalty,
                 stall_steps=args.stall_steps, max_walls=args.walls, robots=args.robots, seed=args.seed,
                 max_minutes=args.max_minutes, stop_after=args.stop_after, checkpoint_minutes=args.checkpoint_minutes, eval_episodes=args.eval_episodes,
                 threads=args.threads, progress=not args.no_progress, plots=not args.no_plots)
    train(job)
    return 0
