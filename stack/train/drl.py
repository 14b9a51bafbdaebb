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
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..argtypes import nonnegative_float, nonnegative_int, positive_int
from . import PROG, InputError
from .flags import add_job_arguments, flag, job_from_args

HELD_OUT_SEED = 20261
COURSE_WORLD = {"robots": 8, "max_circles": 24, "max_boxes": 24}
"""Stage 3's world: room for a course's 3-8 robots and its obstacles (:mod:`.course_scenes`)."""
EVAL_COURSES = 30
"""Stage 3: the courses (seeds ``eval_course_seed`` ..) the end-of-training evaluation cuts its scenes from."""


@dataclass
class DrlJob:
    """What ``stack-train drl`` runs; defaults are Table I where our setting can follow it.

    The command line is generated from these fields (``--field-name``, the docstring as help:
    :mod:`stack.train.flags`), so a setting is written once, here."""

    stage: int = flag(1, choices=(1, 2, 3))
    """curriculum stage: 1 one robot among obstacles, 2 four robots (one trained, the others on a frozen copy),
    3 (ours) stretches of generated courses, 3-8 robots, a curriculum over density and robot count"""
    out: Path = Path("runs/drl")
    """output folder (drl.pt, best.pt, drl.json, reward.png)"""
    init: Path | None = flag(None, metavar="WEIGHTS")
    """start from these weights (stage 2: the stage-1 drl.pt)"""
    evaluate: Path | None = flag(None, metavar="WEIGHTS")
    """only evaluate these weights on the held-out scenes (no training)"""
    export: Path | None = flag(None, metavar="OUT.npz")
    """only write the weights of --init (default: the shipped drl.pt) as the numpy .npz a robot's numpy runtime loads"""
    episodes: int | None = flag(None, type=positive_int)
    """max-episodes (section V-A; None: 5000 in stage 1, 10000 in stage 2)"""
    envs: int = flag(16, type=positive_int)
    """environments stepped together (the paper: one gazebo world)"""
    batch: int = flag(128, type=positive_int)
    """minibatch (Table I: 32)"""
    memory: int = flag(100_000, type=positive_int)
    """replay memory (Table I: 2000)"""
    gamma: float = 0.99
    """discount (Table I)"""
    lr: float = 1e-3
    """Adam learning rate (Table I)"""
    target_every: int = flag(500, type=positive_int)
    """C of Table I: gradient steps between target-network copies"""
    copy_every: int = flag(10_000, type=positive_int)
    """N of Table I: trained-robot transitions between copies to the other robots (stage 2)"""
    eps_start: float | None = None
    """initial epsilon (None: 1.0 in stage 1, 0.5 in stage 2)"""
    eps_end: float = 0.1
    """final epsilon"""
    eps_fraction: float | None = None
    """fraction of the episodes over which epsilon falls (None: 0.6 in stage 1, 0.7 in stage 2)"""
    learn_start: int = flag(1000, type=nonnegative_int)
    """transitions in the replay memory before the first update"""
    updates_per_step: int = flag(1, type=positive_int)
    """gradient steps per parallel step (of ``envs`` transitions)"""
    n_step: int = flag(1, type=positive_int)
    """n-step returns (1: eq. 18 as printed)"""
    huber: bool = flag(True, off="--mse")
    """Huber loss instead of the squared TD error of Algorithm 1 (--mse: squared)"""
    grad_clip: float = flag(10.0, type=nonnegative_float)
    """gradient-norm clip"""
    max_steps: int = flag(500, type=positive_int)
    """max-step per episode (Table I)"""
    time_penalty: float = flag(0.0, type=nonnegative_float)
    """ours: subtract this from every step's reward until arrival (0: eq. 14-17 as printed)"""
    collision_penalty: float = flag(1.0, type=nonnegative_float)
    """ours: a collision's reward is minus this (1: eq. 16 as printed)"""
    stall_steps: int = flag(0, type=nonnegative_int)
    """ours: end an episode with -(stall penalty) when the robot has moved < 0.1 m in this many steps (0: off)"""
    stall_penalty: float = flag(1.0, type=nonnegative_float)
    """ours: the reward of a stall that ends an episode is minus this (--stall-steps)"""
    robots: int = flag(4, choices=range(2, 9), metavar="N")
    """stage 2: robots per scene, 2..8 (the paper: four)"""
    courses: int = flag(240, type=positive_int)
    """stage 3: generated courses in the training pool (seeds --course-seed ..; each density and 3-8 robots in turn)"""
    course_seed: int = flag(0, type=nonnegative_int)
    """stage 3: the pool's first course seed (training seeds; the held-out 1,000,000.. are refused)"""
    eval_course_seed: int = flag(900, type=nonnegative_int)
    """stage 3: the first seed of the 30 courses the end-of-training evaluation cuts its scenes from"""
    follow: bool = False
    """stage 3 (ours): the targets move as in a fleet: robot 0 leads (eq. 20 and the hold), the others drive to
    their slots round it (eq. 3) for 10-25 m and arrive only once it has stopped"""
    max_walls: int = flag(2, name="--walls", choices=range(0, 4), metavar="N")
    """walls (2-10 m, across the way) per training / held-out scene, 0..N (0: the paper's randomly scattered
    cuboids and cylinders)"""
    seed: int = 0
    """seed of the worlds, the exploration and torch"""
    max_minutes: float | None = None
    """stop (and save, and evaluate) after this wall time [min]; the epsilon schedule and stage 3's curriculum
    then follow whichever of the episodes and the time is further along"""
    stop_after: int | None = flag(None, type=positive_int, metavar="EPISODES")
    """stop after this many episodes (the epsilon schedule still spans --episodes): replays a run cut by
    --max-minutes"""
    checkpoint_minutes: float = 3.0
    """write drl.pt this often"""
    eval_episodes: int = flag(200, type=nonnegative_int)
    """held-out episodes at the end (0: none)"""
    eval_seed: int = HELD_OUT_SEED
    """the held-out scenes' seed (another one: a fresh set nobody chose weights on)"""
    threads: int = flag(1, type=positive_int)
    """torch threads"""
    overlap: bool = True
    """learn on a second thread while the world steps (two cores): gradient step k samples the replay memory as it
    was before parallel step k's transitions went in, and the robots act on theta after step k-1 as before; the run
    stays deterministic per seed. --no-overlap: one thread, step then learn"""
    progress: bool = True
    """a live progress bar"""
    plots: bool = True
    """write reward.png"""
    extra: dict = flag(default_factory=dict, cli=False)
    """free-form notes carried into drl.json"""

    def __post_init__(self) -> None:
        if self.episodes is None:
            self.episodes = 5000 if self.stage == 1 else 10000

    def epsilon(self, episode: int, done: float | None = None) -> float:
        """Epsilon after ``episode`` episodes, or at the fraction ``done`` of the training (``Trainer.done``)."""
        e0 = self.eps_start if self.eps_start is not None else (1.0 if self.stage == 1 else 0.5)
        frac = self.eps_fraction if self.eps_fraction is not None else (0.6 if self.stage == 1 else 0.7)
        done = episode / self.episodes if done is None else done
        k = min(1.0, done / max(1.0 / self.episodes, frac))
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
             epsilon: float = 0.0, max_walls: int = 2, robots: int = 4, course_seed: int = 900,
             follow: bool = False) -> dict:
    """Greedy run of ``net`` on the held-out scenes: success / collision / timeout rates.

    Stage 1: one robot per scene. Stage 2: all four robots drive with ``net``; a scene succeeds
    when every robot arrives, fails by collision when any collides. Stage 3: the same on scenes cut
    from the courses of seeds ``course_seed`` .. (not the training pool's; every curriculum level). ``epsilon``: the chance of a
    random action per step (the policy's ``explore``; 0: greedy). ``follow``: stage 3's moving slots."""
    import torch

    from stack.policies.drl.observation import ACTIONS

    from .drlworld import DrlWorld, WorldConfig, held_out_scenes

    if stage == 3:  # scenes cut from courses no training pool holds, every curriculum level
        pool = course_pool(EVAL_COURSES, course_seed, log=lambda *_: None, follow=follow)
        pool.progress, rng = 1.0, np.random.default_rng([seed, stage])
        scenes = [pool(rng) for _ in range(episodes)]
        cfg = WorldConfig(max_steps=max_steps, follow=follow, **COURSE_WORLD)
    else:
        scenes = held_out_scenes(episodes, stage, seed, max_walls, robots)
        cfg = WorldConfig(max_steps=max_steps, max_walls=max_walls, robots=robots)
    w = DrlWorld(episodes, stage, seed=seed + 1, cfg=cfg)
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
    succ = (arrived | ~w.present).all(axis=1) & ~collided.any(axis=1)  # every robot in the scene arrived
    coll = collided.any(axis=1)
    return {"episodes": episodes, "stage": stage, "seed": seed, "epsilon": epsilon, "max_walls": max_walls, "robots": w.R,
            "follow": follow, "success": float(succ.mean()), "collision": float(coll.mean()),
            "timeout": float((~succ & ~coll).mean()), "mean_steps_success": float(steps[succ].mean()) if succ.any() else None}


def course_pool(n: int, first_seed: int, log=print, follow: bool = False):
    """Stage 3's scenes: :class:`.course_scenes.CourseScenes` of ``n`` generated courses."""
    from .course_scenes import CourseScenes

    t0 = time.monotonic()
    pool = CourseScenes(n, first_seed, follow=follow)
    log(f"stage 3: {n} generated courses (seeds {first_seed}..{first_seed + n - 1}) in {time.monotonic() - t0:.1f} s")
    return pool


# --- training ----------------------------------------------------------------------------------------
class _Training:
    """One run of Algorithm 1: the world, the learner, the frozen copy (stage 2), the curve."""

    def __init__(self, job: DrlJob, log):
        import torch

        from stack.policies.drl.network import DuelingQNet
        from stack.policies.drl.observation import ACTIONS

        from .drlworld import DrlWorld, WorldConfig

        self.torch, self.job, self.log, self.actions = torch, job, log, ACTIONS
        torch.set_num_threads(job.threads)
        torch.manual_seed(job.seed)
        self.rng = np.random.default_rng(job.seed)
        job.out.mkdir(parents=True, exist_ok=True)
        net = DuelingQNet()
        if job.init:
            net.load_state_dict(torch.load(job.init, map_location="cpu", weights_only=True))
        self.L = Learner(job, net)
        self.actor = DuelingQNet()  # theta as the trained robots act on it (a copy: the learner's thread changes theta)
        self.actor.load_state_dict(net.state_dict())
        self.frozen = DuelingQNet()  # theta~ of the other robots (stage 2)
        self.frozen.load_state_dict(net.state_dict())
        self.scenes = course_pool(job.courses, job.course_seed, log, job.follow) if job.stage == 3 else None
        size = COURSE_WORLD if job.stage == 3 else {"robots": job.robots}
        self.world = DrlWorld(job.envs, job.stage, seed=job.seed, scenes=self.scenes, cfg=WorldConfig(
            max_steps=job.max_steps, time_penalty=job.time_penalty, stall_steps=job.stall_steps,
            stall_penalty=job.stall_penalty, collision_penalty=job.collision_penalty, max_walls=job.max_walls, follow=job.follow, **size))
        self.N, self.R = self.world.N, self.world.R
        self.D = Replay(job.memory, self.world.cfg.beams, self.R - 1, self.rng)
        self.nstep = NStep(self.D, job.n_step, job.gamma, self.N)
        self.rows = np.arange(self.N)
        self.ep_return = np.zeros(self.N)
        self.curve: list[dict] = []
        self.losses: list[float] = []
        self.best, self.since_copy, self.steps, self.episode = -math.inf, 0, 0, 0
        self.t0 = self.last_ckpt = time.monotonic()
        self.bar = None
        if job.progress:
            from tqdm import tqdm

            self.bar = tqdm(total=job.episodes, desc=f"drl stage {job.stage}", unit="ep", dynamic_ncols=True, mininterval=2.0)

    def save(self, path: Path) -> None:
        self.torch.save(self.L.q.state_dict(), path)

    def act(self, obs: dict, eps: float) -> tuple[np.ndarray, np.ndarray, dict]:
        """(actions (N, R), the trained robots' actions (N,), their observations): epsilon-greedy on theta for
        the trained robot of each environment, greedy on theta~ for the others."""
        N, R, rows, tr = self.N, self.R, self.rows, self.world.trained
        o = pick(obs, rows, tr)
        a_tr = greedy(self.actor, o, self.torch)
        explore = self.rng.random(N) < eps
        a_tr[explore] = self.rng.integers(0, len(self.actions), explore.sum())
        actions = np.zeros((N, R), np.int64)
        if R > 1:
            others = np.ones((N, R), bool)
            others[rows, tr] = False
            rr, cc = np.nonzero(others)
            actions[rr, cc] = greedy(self.frozen, pick(obs, rr, cc), self.torch)
        actions[rows, tr] = a_tr
        return actions, a_tr, o

    def step(self, obs: dict, eps: float) -> tuple[dict, np.ndarray]:
        """One parallel step: act, store the trained robots' transitions, close the finished episodes."""
        w, rows, tr = self.world, self.rows, self.world.trained
        actions, a_tr, o = self.act(obs, eps)
        r, arrived, collided, done, _ = w.step(actions, self.actions)
        obs2 = w.observe()
        term = (arrived[rows, tr] | collided[rows, tr] | w.stalled[rows, tr]).astype(np.float32)
        self.nstep.push(o, a_tr, r[rows, tr], pick(obs2, rows, tr), term, done)
        self.ep_return += r[rows, tr]
        self.steps += self.N
        self.since_copy += self.N
        for n in np.nonzero(done)[0]:
            self.episode += 1
            outcome = ("arrived" if arrived[n, tr[n]] else "collided" if collided[n, tr[n]]
                       else "stalled" if w.stalled[n, tr[n]] else "timeout")
            self.curve.append({"episode": self.episode, "return": round(float(self.ep_return[n]), 3), "outcome": outcome,
                               "steps": int(w.t[n]), "epsilon": round(eps, 4)})
        if done.any():
            self.ep_return[done] = 0.0
            if self.scenes is not None:  # stage 3's curriculum: the new scenes at the training's progress
                self.scenes.progress = self.done()
            w.reset(done)
            obs2 = w.observe()
        return obs2, done

    def batches(self) -> list:
        """The minibatches of this parallel step's gradient steps (none until the memory holds enough)."""
        job = self.job
        if self.D.n < max(job.learn_start, job.batch):
            return []
        return [self.D.sample(job.batch) for _ in range(job.updates_per_step)]

    def update(self, batches: list) -> None:
        """The gradient steps (on the learner's thread with ``overlap``: touches theta, theta^- and the losses only)."""
        for b in batches:
            self.losses.append(self.L.update(b))

    def synced(self) -> None:
        """After the gradient steps: the acting copy of theta; theta~ = theta every N transitions (stage 2)."""
        self.actor.load_state_dict(self.L.q.state_dict())
        if self.R > 1 and self.since_copy >= self.job.copy_every:
            self.frozen.load_state_dict(self.L.q.state_dict())  # every N steps theta~ = theta
            self.since_copy = 0

    def report(self, eps: float) -> None:
        """After episodes ended: best.pt on a new best 50-episode mean (epsilon at its floor), the progress bar."""
        recent = self.curve[-50:]
        mean50 = float(np.mean([c["return"] for c in recent]))
        if len(self.curve) >= 50 and eps <= self.job.eps_end + 1e-9 and mean50 > self.best:
            self.best = mean50
            self.save(self.job.out / "best.pt")
        if self.bar is not None:
            self.bar.n = min(self.episode, self.job.episodes)
            succ = np.mean([c["outcome"] == "arrived" for c in recent])
            self.bar.set_postfix(eps=f"{eps:.2f}", reward50=f"{mean50:.2f}", success50=f"{succ:.2f}",
                                 loss=f"{np.mean(self.losses[-100:]) if self.losses else 0:.3f}",
                                 steps_s=f"{self.steps / (time.monotonic() - self.t0):.0f}", refresh=False)
            self.bar.update(0)

    def checkpoint(self) -> None:
        if time.monotonic() - self.last_ckpt > 60 * self.job.checkpoint_minutes:
            self.save(self.job.out / "drl.pt")
            _write_json(self.job, self.curve, self.losses, self.steps, time.monotonic() - self.t0, None)
            self.last_ckpt = time.monotonic()

    def done(self) -> float:
        """How far the training is, 0..1: of its episodes, or of ``max_minutes`` where that comes first (the
        epsilon schedule and stage 3's curriculum follow it, so a run cut by time still reaches every level)."""
        f = self.episode / self.job.episodes
        if self.job.max_minutes:
            f = max(f, (time.monotonic() - self.t0) / (60 * self.job.max_minutes))
        return min(1.0, f)

    def stop(self) -> bool:
        job = self.job
        if job.max_minutes and time.monotonic() - self.t0 > 60 * job.max_minutes:
            self.log(f"time limit: {job.max_minutes} min reached after {self.episode} episodes")
            return True
        return bool(job.stop_after and self.episode >= job.stop_after)

    def run(self) -> dict:
        from concurrent.futures import ThreadPoolExecutor

        obs = self.world.observe()
        with ThreadPoolExecutor(1, thread_name_prefix="learner") as learner:
            while self.episode < self.job.episodes and not self.stop():
                eps = self.job.epsilon(self.episode, self.done())
                if self.job.overlap:  # the gradient steps on the learner's thread while the world steps
                    pending = learner.submit(self.update, self.batches())
                    obs, done = self.step(obs, eps)
                    pending.result()
                else:
                    obs, done = self.step(obs, eps)
                    self.update(self.batches())
                self.synced()
                if self.curve and done.any():
                    self.report(eps)
                self.checkpoint()
        if self.bar is not None:
            self.bar.close()
        return self.finish(time.monotonic() - self.t0)

    def finish(self, wall: float) -> dict:
        """drl.pt, the held-out evaluation of drl.pt (and best.pt), drl.json, reward.png."""
        job = self.job
        self.save(job.out / "drl.pt")
        self.log(f"{self.episode} episodes, {self.steps} env steps in {wall:.0f} s "
                 f"({self.steps / wall:.0f} env steps/s), {self.L.steps} gradient steps")
        ev = None
        if job.eval_episodes:
            from stack.policies.drl.network import DuelingQNet

            nets = {"drl.pt": self.L.q}
            if (job.out / "best.pt").exists():
                nets["best.pt"] = DuelingQNet()
                nets["best.pt"].load_state_dict(self.torch.load(job.out / "best.pt", weights_only=True))
            ev = {k: evaluate(net, stage=job.stage, episodes=job.eval_episodes, max_steps=job.max_steps,
                              max_walls=job.max_walls, robots=job.robots, seed=job.eval_seed,
                              course_seed=job.eval_course_seed, follow=job.follow) for k, net in nets.items()}
            for k, v in ev.items():
                self.log(f"held-out {k}: success {v['success']:.3f}, collision {v['collision']:.3f}, timeout {v['timeout']:.3f}")
        summary = _write_json(job, self.curve, self.losses, self.steps, wall, ev)
        if job.plots:
            _plot(self.curve, job.out / "reward.png", job.stage)
        return summary


def train(job: DrlJob, log=print) -> dict:
    """Algorithm 1 as ``job`` says; returns what OUT/drl.json holds."""
    return _Training(job, log).run()


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
    add_job_arguments(p, DrlJob)  # one flag per DrlJob field


def main(args: argparse.Namespace) -> int:
    import torch

    from stack.policies.drl.network import DuelingQNet

    job = job_from_args(DrlJob, args)
    for path in (job.evaluate, job.init):
        if path is not None and not path.exists():
            raise InputError(f"{path}: no such weights file")
    if job.follow and job.stage != 3:
        raise InputError(f"--follow: only stage 3 has a leader to follow (got --stage {job.stage})")
    if job.stage == 3:
        from .course_scenes import heldout_clash

        for flag_, first, n in (("--course-seed", job.course_seed, job.courses),
                                ("--eval-course-seed", job.eval_course_seed, EVAL_COURSES)):
            if heldout_clash(first, n):
                raise InputError(f"{flag_} {first}: {heldout_clash(first, n)}")
    if job.export:
        from stack.policies.drl.numpy_net import export_npz
        from stack.policies.drl.policy import WEIGHTS, load_network

        print(f"{PROG} drl: wrote {export_npz(load_network(job.init or WEIGHTS).state_dict(), job.export)}")
        return 0
    if job.evaluate:
        torch.set_num_threads(job.threads)
        net = DuelingQNet()
        net.load_state_dict(torch.load(job.evaluate, map_location="cpu", weights_only=True))
        print(json.dumps(evaluate(net, stage=job.stage, episodes=job.eval_episodes or 200, max_steps=job.max_steps,
                                  max_walls=job.max_walls, robots=job.robots, seed=job.eval_seed,
                                  course_seed=job.eval_course_seed, follow=job.follow)))
        return 0
    train(job)
    return 0
