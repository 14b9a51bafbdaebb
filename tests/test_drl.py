"""Bai 2022 DRL policy: observation, reward, network, the numpy training world, training, shipped weights."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest
import torch  # the test install has it (a missing one is a failure, not a skip)

torch.set_num_threads(1)  # as in every agent process; more threads only contend on a loaded machine

from conftest import scenario_dict  # noqa: E402
from stack.policies.base import Observation  # noqa: E402
from stack.policies.drl.network import DuelingQNet  # noqa: E402
from stack.policies.drl.observation import ACTIONS, goal_features, neighbour_features, scan_features  # noqa: E402
from stack.policies.drl.reward import reward  # noqa: E402
from stack.train.drlworld import DrlWorld, WorldConfig, ray_cast, scene_arrays  # noqa: E402


# --- observation, actions, reward ---------------------------------------------------------
def test_actions_are_the_papers_fifteen():
    assert ACTIONS.shape == (15, 2)
    assert sorted(set(ACTIONS[:, 0])) == [0.0, 0.5, 1.0]
    assert sorted(set(ACTIONS[:, 1])) == [-1.0, -0.5, 0.0, 0.5, 1.0]


def test_normalisation_eq_11_13():
    g = goal_features(1.5, math.pi / 2, 0.5, -0.2)
    assert np.allclose(g, [0.5, 0.5, 0.5, -0.2])
    assert goal_features(7.0, -math.pi, 0, 0)[0] == 1.0  # clipped at d_n = 3 m
    assert np.allclose(neighbour_features([[5.0, math.pi / 4], [2.0, 0.0]]), [[0.5, 0.25], [0.2, 0.0]])
    s = scan_features(np.full((2, 180), 2.5))
    assert s.shape == (3, 180) and np.allclose(s, 0.5)  # two scans: the oldest repeated
    assert scan_features(np.zeros((0, 0))).shape == (3, 180)
    assert np.allclose(scan_features(np.full((3, 90), 10.0)), 1.0)  # resampled, clipped at 5 m


@pytest.mark.parametrize("case, args, expect, arrived, collided", [
    ("progress", (3.0, 2.9, np.inf, 4.0, (1, 0), (1, 0)), 0.05, False, False),
    ("arrival", (0.6, 0.5, np.inf, 4.0, (1, 0), (1, 0)), 20.0, True, False),
    ("robot collision", (3.0, 3.0, 0.99, 4.0, (0, 0), (0, 0)), -1.0, False, True),
    ("obstacle collision", (3.0, 3.0, np.inf, 0.49, (0, 0), (0, 0)), -1.0, False, True),
    ("near robot", (3.0, 3.0, 1.4, 4.0, (0, 0), (0, 0)), -0.3, False, False),
    ("near obstacle", (3.0, 3.0, np.inf, 0.9, (0, 0), (0, 0)), -0.3, False, False),
    ("action change", (3.0, 3.0, np.inf, 4.0, (0.0, -1.0), (1.0, 0.5)), -0.05 * 2.5, False, False),
    ("all terms", (1.0, 0.8, 1.2, 4.0, (0.5, 0.0), (1.0, 0.0)), 0.1 - 0.3 - 0.025, False, False),
])
def test_reward_eq_14_17(case, args, expect, arrived, collided):
    r, a, c = reward(*args)
    assert math.isclose(float(r), expect, abs_tol=1e-9), case
    assert bool(a) == arrived and bool(c) == collided


# --- network ---------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [0, 1, 7])
def test_network_shapes(n):
    net = DuelingQNet()
    q = net(torch.rand(5, 3, 180), torch.rand(5, 4), torch.rand(5, n, 2))
    assert q.shape == (5, 15)
    from stack.policies.drl.policy import DrlPolicy

    p = DrlPolicy(net=net)
    obs = Observation(d_g=4.0, alpha_g=0.3, v=0.5, w=0.0, neighbours=np.random.rand(n, 2) * [10, 3], scans=np.full((3, 180), 5.0))
    v, w = p.act(obs)
    assert (v, w) in {tuple(a) for a in ACTIONS.tolist()}


def test_padded_neighbours_equal_unpadded():
    torch.manual_seed(0)
    net = DuelingQNet().eval()
    s, g = torch.rand(3, 3, 180), torch.rand(3, 4)
    seqs = [torch.rand(k, 2) for k in (0, 2, 4)]
    pad = torch.zeros(3, 4, 2)
    for i, q in enumerate(seqs):
        pad[i, : len(q)] = q
    batched = net(s, g, pad, torch.tensor([0, 2, 4]))
    for i, q in enumerate(seqs):
        one = net(s[i:i + 1], g[i:i + 1], q[None])
        assert torch.allclose(batched[i], one[0], atol=1e-6)


# --- the numpy world against pybullet -----------------------------------------------------------
def _random_scene(rng):
    obs = []
    for _ in range(rng.integers(1, 6)):
        obs.append({"type": "cylinder", "x": float(rng.uniform(-6, 6)), "y": float(rng.uniform(-6, 6)), "radius": float(rng.uniform(0.2, 1.0))})
    for _ in range(rng.integers(1, 5)):
        obs.append({"type": "box", "x": float(rng.uniform(-6, 6)), "y": float(rng.uniform(-6, 6)), "size_x": float(rng.uniform(0.3, 2.5)),
                    "size_y": float(rng.uniform(0.3, 2.5)), "yaw_deg": float(rng.uniform(-180, 180))})
    for _ in range(rng.integers(0, 3)):
        a, b = rng.uniform(-7, 7, 2), rng.uniform(-7, 7, 2)
        obs.append({"type": "wall", "from": [float(a[0]), float(a[1])], "to": [float(b[0]), float(b[1])], "thickness": 0.2})
    return obs


def test_numpy_lidar_equals_pybullet():
    """Every well-conditioned beam within 1 cm of pybullet's ``rayTestBatch``.

    A beam that grazes a body (passes within 5 mm of a circle's tangent or a box's corner) is
    ill-conditioned: a 1 mm change of geometry flips it between a hit metres away and a miss,
    and Bullet's float32 ray tests differ from exact geometry there by up to a few cm. Such beams
    are found by casting against every body grown and shrunk by 5 mm (the two disagree by > 10 cm) and
    are not compared; they must stay rare."""
    from stack.scenario import parse_scenario
    from stack.sim_bridge.geometry import distance_to_obstacles
    from stack.sim_bridge.world import World

    rng = np.random.default_rng(7)
    checked = grazing = 0
    eps = 0.005
    for _ in range(12):
        obstacles = _random_scene(rng)
        robots = [{"id": i, "role": "leader" if i == 0 else "follower", "pose": [0.0, 0.0, 0.0]} for i in range(4)]
        sc = parse_scenario(scenario_dict(world={"obstacles": obstacles}, robots=robots), "drl.yaml")
        world = World(sc)
        circles, boxes = scene_arrays(sc.obstacles)
        for _ in range(5):
            pts = []  # robots clear of every body (a ray starting inside one is not compared)
            while len(pts) < 4:
                p = rng.uniform(-7, 7, 2)
                if distance_to_obstacles(p[0], p[1], sc.obstacles) > 0.6 and all(math.hypot(*(p - q)) > 1.1 for q in pts):
                    pts.append(p)
            pts = np.array(pts)
            world.x[:], world.y[:], world.yaw[:] = pts[:, 0], pts[:, 1], rng.uniform(-math.pi, math.pi, 4)
            world._sync_bodies()
            ref = world.lidar()
            for i in range(4):
                circ = np.vstack([circles, [[world.x[j], world.y[j], 0.5] for j in range(4) if j != i]])
                args = (np.array(world.x[i]), np.array(world.y[i]), np.array(world.yaw[i]))
                cast = lambda c, b: ray_cast(*args, c, b, world.beam_angles[i], 0.51, 5.0)  # noqa: E731
                r = cast(circ, boxes)
                grow, shrink = np.array([0, 0, eps]), np.array([0, 0, eps, eps, 0])
                ok = np.abs(cast(circ + grow, boxes + shrink) - cast(circ - grow, boxes - shrink)) < 0.1
                assert np.abs(r - ref[i])[ok].max() < 0.01, np.sort(np.abs(r - ref[i])[ok])[-5:]
                checked += ok.sum()
                grazing += (~ok).sum()
        world.close()
    assert checked + grazing == 12 * 5 * 4 * 180
    print(f"compared {checked} beams, {grazing} grazing")
    assert grazing < 0.01 * checked, (grazing, checked)


def test_world_steps_like_the_unicycle_and_detects_collisions():
    w = DrlWorld(2, 1, seed=0)
    w.circles[:] = [1e4, 1e4, 0.0]
    w.boxes[:] = [1e4, 1e4, 0, 0, 0]
    w.circles[1, 0] = [2.0, 0.0, 0.5]
    w.x[:], w.y[:], w.yaw[:], w.gx[:], w.gy[:] = 0.0, 0.0, 0.0, 20.0, 0.0
    for _ in range(30):
        r, arr, col, done, _ = w.step(np.full((2, 1), 12), ACTIONS)  # v = 1, w = 0
        if done[1]:
            break
    assert col[1, 0] and not w.active[1, 0] and w.active[0, 0]
    assert 1.0 < w.x[1, 0] <= 1.1 and abs(w.y[0, 0]) < 1e-9  # stopped within the step that came within R_d


def test_time_penalty_and_stall_end_a_standing_robots_episode():
    """Our training additions: every step that does not arrive costs time_penalty, and a robot that has
    moved less than stall_move in stall_steps ends its episode with -stall_penalty (the evaluation keeps both off)."""
    r0, _, _ = reward(5.0, 5.0, math.inf, 3.0, np.zeros(2), np.zeros(2))
    r1, _, _ = reward(5.0, 5.0, math.inf, 3.0, np.zeros(2), np.zeros(2), time_penalty=0.01)
    ra, arrived, _ = reward(0.6, 0.4, math.inf, 3.0, np.zeros(2), np.zeros(2), time_penalty=0.01)
    assert r0 == 0.0 and r1 == pytest.approx(-0.01) and arrived and ra == pytest.approx(20.0)
    w = DrlWorld(2, 1, seed=0, cfg=WorldConfig(stall_steps=30, time_penalty=0.01))
    w.circles[:] = [1e4, 1e4, 0.0]
    w.boxes[:] = [1e4, 1e4, 0, 0, 0]
    w.x[:], w.y[:], w.yaw[:], w.gx[:], w.gy[:] = 0.0, 0.0, 0.0, 20.0, 0.0
    w.anchor[:] = 0.0
    stand, drive = 2, 12  # (0, 0) and (1, 0)
    for k in range(30):
        r, arr, col, done, _ = w.step(np.array([[stand], [drive]]), ACTIONS)
        if k < 29:
            assert not done.any() and not w.stalled.any()
    assert w.stalled[0, 0] and done[0] and r[0, 0] == pytest.approx(-1.01)
    assert not w.stalled[1, 0] and w.active[1, 0] and not col.any()


def test_the_stall_penalty_flag_reaches_the_training_world(tmp_path):
    """``stack-train drl --stall-penalty P`` (ours): a stall that ends an episode costs P, in the world trained in."""
    from stack.train.drl import DrlJob, _Training

    job = DrlJob(stage=1, out=tmp_path, envs=2, stall_steps=30, stall_penalty=5.0, collision_penalty=10.0)
    cfg = _Training(job, log=lambda *_: None).world.cfg
    assert (cfg.stall_steps, cfg.stall_penalty, cfg.collision_penalty) == (30, 5.0, 10.0)


# --- training -------------------------------------------------------------------------------------
def test_td_loss_decreases_and_a_short_run_writes_its_outputs(tmp_path):
    from stack.train.drl import DrlJob, Learner, Replay, pick, train

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    w = DrlWorld(8, 2, seed=1, cfg=None)
    D = Replay(2000, 180, 3, rng)
    rows = np.arange(8)
    obs = w.observe()
    for _ in range(60):  # random play, the trained robot's transitions
        a = rng.integers(0, 15, (8, 4))
        r, arr, col, done, _ = w.step(a, ACTIONS)
        obs2 = w.observe()
        D.add(pick(obs, rows, w.trained), a[rows, w.trained], r[rows, w.trained], pick(obs2, rows, w.trained),
              (arr | col)[rows, w.trained].astype(np.float32), 0.99)
        w.reset(done)
        obs = w.observe()
    L = Learner(DrlJob(lr=1e-3))
    everything = D.get(np.arange(D.n))
    with torch.no_grad():
        before = float(L.loss(everything))
    for _ in range(80):
        L.update(D.sample(64))
    with torch.no_grad():
        after = float(L.loss(everything))
    assert after < 0.7 * before, (before, after)

    job = DrlJob(stage=2, out=tmp_path, episodes=6, envs=4, batch=16, learn_start=32, max_steps=40, copy_every=50,
                 eval_episodes=4, progress=False, plots=True)
    s = train(job, log=lambda *_: None)
    assert s["episodes"] >= 6 and s["gradient_steps"] > 0
    assert (tmp_path / "drl.pt").exists() and (tmp_path / "reward.png").exists()
    assert set(s["evaluation"]["drl.pt"]) >= {"success", "collision", "timeout"}


class _RandomQ(torch.nn.Module):
    def forward(self, scans, *_):
        return torch.rand(scans.shape[0], 15)


def test_shipped_weights_beat_a_random_policy():
    from stack.policies.drl.policy import WEIGHTS, load_network
    from stack.train.drl import evaluate

    torch.manual_seed(0)
    trained = evaluate(load_network(WEIGHTS), stage=1, episodes=40, max_steps=300)
    random = evaluate(_RandomQ(), stage=1, episodes=40, max_steps=300)
    assert trained["success"] >= random["success"] + 0.3, (trained, random)
    assert trained["collision"] < random["collision"]


def test_default_policy_loads_the_shipped_weights():
    from stack.policies.drl.policy import make_drl

    p = make_drl(None, seed=3)
    assert p.name == "drl" and p.hybrid
    assert torch.get_num_threads() == 1
    v, w = p.act(Observation(d_g=5.0, alpha_g=0.0, v=0.0, w=0.0, scans=np.full((1, 180), 5.0)))
    assert v > 0 and abs(w) <= 0.5  # open space, goal straight ahead: drive toward it


class _FixedQ(torch.nn.Module):
    """Always prefers action ``best`` (then the others in index order)."""

    def __init__(self, best: int):
        super().__init__()
        self.best = best

    def forward(self, scans, *_):
        q = -torch.arange(15, dtype=torch.float32).repeat(scans.shape[0], 1) * 0.01
        q[:, self.best] = 1.0
        return q


def test_shield_masks_the_actions_that_would_hit_what_the_scan_sees():
    from stack.policies.drl.config import DrlConfig
    from stack.policies.drl.policy import DrlPolicy, Shield

    sh = Shield(ACTIONS, radius=0.5, fov=math.pi, horizon=0.6, margin=0.1)
    ahead = np.full(180, 5.0)
    ahead[85:95] = 1.0  # a wall 1 m straight ahead
    ok = sh.safe(ahead, 5.0)
    assert not ok[ACTIONS[:, 0] == 1.0].any()  # 0.6 m at 1 m/s: within radius + margin of it
    assert ok[ACTIONS[:, 0] == 0.0].all()  # standing and turning on the spot are always allowed
    assert sh.safe(np.full(180, 5.0), 5.0).all()  # nothing in range: everything allowed
    th = np.linspace(-math.pi / 2, math.pi / 2, 180)
    wall = np.where(th > 0.2, np.minimum(0.55 / np.maximum(np.sin(th), 1e-6), 5.0), 5.0)  # a wall 0.55 m to the left
    ok = sh.safe(wall, 5.0)
    assert ok[12] and ok[10] and not ok[14]  # already near it: along it or away is allowed, into it is not
    fast = 12  # (1, 0)
    obs = Observation(d_g=5.0, alpha_g=0.0, v=1.0, w=0.0, scans=np.stack([ahead] * 3))
    shielded = DrlPolicy(net=_FixedQ(fast), cfg=DrlConfig(shield=True))
    v, w = shielded.act(obs)
    assert v < 1.0 and shielded.masked == 1  # the network's choice is overruled, the best allowed one taken
    alone = DrlPolicy(net=_FixedQ(fast), cfg=DrlConfig(shield=False))
    assert alone.act(obs) == (1.0, 0.0) and alone.masked == 0


def test_robot_drl_settings_reach_the_policy(tmp_path):
    from stack.policies.drl.policy import WEIGHTS, make_drl
    from stack.scenario import ScenarioError, parse_scenario

    d = scenario_dict()
    d["robot"]["drl"] = {"shield": False, "weights": str(WEIGHTS)}
    sc = parse_scenario(d, "s.yaml")
    p = make_drl(sc.robots[0])
    assert p.shield is None and p.cfg.weights == str(WEIGHTS)
    d["robot"]["drl"] = {"shield_margin": 0.2}
    p = make_drl(parse_scenario(d, "s.yaml").robots[1])
    assert p.shield is not None and p.shield.clear == pytest.approx(sc.robots[1].radius + 0.2)
    assert p.leader_hold == (0.8, 0.95)  # the default: the leader waits before a follower falls out of range
    d["robot"]["drl"] = {"leader_hold": None}
    assert make_drl(parse_scenario(d, "s.yaml").robots[0]).leader_hold is None  # eq. (20) alone
    d["robot"]["drl"] = {"leader_hold": [0.5, 0.9]}
    assert make_drl(parse_scenario(d, "s.yaml").robots[0]).leader_hold == (0.5, 0.9)
    for bad in ([0.9, 0.8], [0.8], [0.8, 1.2], "near", [True, 0.9]):
        d["robot"]["drl"] = {"leader_hold": bad}
        with pytest.raises(ScenarioError, match=r"robot\.drl.*leader_hold: expected \[start, stop\]"):
            parse_scenario(d, "s.yaml")


def test_the_collision_penalty_replaces_eq_16s_minus_one_and_nothing_else():
    args = ([2.0, 2.0], [1.9, 1.9], [0.8, 5.0], [5.0, 5.0], np.zeros((2, 2)), np.zeros((2, 2)))
    r1, _, c1 = reward(*args)
    r5, _, c5 = reward(*args, collision_penalty=5.0)
    assert c1.tolist() == c5.tolist() == [True, False]
    assert r1[0] == pytest.approx(0.05 - 1.0) and r5[0] == pytest.approx(0.05 - 5.0)  # eq. (15) progress + r_c
    assert r1[1] == r5[1] == pytest.approx(0.05)


def test_overlapped_learning_is_deterministic_and_samples_the_memory_before_the_step(tmp_path, monkeypatch):
    """``--overlap`` (the default) learns on a second thread while the world steps: the same seed gives the same
    weights bit for bit; each gradient step's batch is drawn before that parallel step's transitions go in, while
    ``--no-overlap`` draws it after; the robots act on a copy of theta that the learner's thread never touches."""
    from stack.train import drl as drl_mod
    from stack.train.drl import DrlJob, train

    def run(out, overlap):
        job = DrlJob(stage=2, out=out, episodes=8, envs=4, batch=16, learn_start=32, max_steps=30, copy_every=50,
                     eval_episodes=0, progress=False, plots=False, seed=5, overlap=overlap)
        return train(job, log=lambda *_: None), torch.load(out / "drl.pt", weights_only=True)

    events = []  # ("batch", memory size) and ("step", size before, size after), in order
    real_batches, real_step = drl_mod._Training.batches, drl_mod._Training.step

    def batches(self):
        events.append(("batch", self.D.n))
        self.theta_now = {k: v.clone() for k, v in self.L.q.state_dict().items()}  # before this step's update
        return real_batches(self)

    def step(self, obs, eps):
        if self.job.overlap:  # theta after the last update, whatever the learner's thread does to theta meanwhile
            assert all(torch.equal(v, self.theta_now[k]) for k, v in self.actor.state_dict().items())
        n = self.D.n
        out = real_step(self, obs, eps)
        events.append(("step", n, self.D.n))
        return out

    def pairs():  # (the batch's memory size, the step it belongs to: before, after)
        return [(e[1], f[1:]) for e, f in zip(events, events[1:]) if e[0] == "batch" and f[0] == "step"]

    monkeypatch.setattr(drl_mod._Training, "batches", batches)
    monkeypatch.setattr(drl_mod._Training, "step", step)
    s1, w1 = run(tmp_path / "a", True)
    assert [e[0] for e in events[:2]] == ["batch", "step"]  # overlap: the batch is drawn, then the world steps
    grew = [(n, before, after) for n, (before, after) in pairs() if after > before]
    assert grew and all(n == before for n, before, _ in grew)  # without that step's transitions
    events.clear()
    s2, w2 = run(tmp_path / "b", True)
    assert s1["gradient_steps"] == s2["gradient_steps"] > 0
    assert all(torch.equal(w1[k], w2[k]) for k in w1)
    events.clear()
    _, w3 = run(tmp_path / "c", False)
    after_step = [(f[2], e[1]) for f, e in zip(events, events[1:]) if f[0] == "step" and e[0] == "batch"]
    assert events[0][0] == "step" and after_step and all(a == n for a, n in after_step)  # with them
    assert any(not torch.equal(w1[k], w3[k]) for k in w1)


def test_the_training_worlds_float32_rays_read_as_float64s_do():
    """The training world casts its rays in float32 (a quarter faster): within 0.1 mm of float64 on its scenes."""
    w = DrlWorld(16, 2, seed=9, cfg=WorldConfig(robots=6, noise_std=0.0))
    x, y, yaw = w.x + w.rng.normal(0, 0.5, w.x.shape), w.y + w.rng.normal(0, 0.5, w.y.shape), w.yaw
    circ = np.broadcast_to(w.circles[:, None], (16, 6) + w.circles.shape[1:])
    boxes = np.broadcast_to(w.boxes[:, None], (16, 6) + w.boxes.shape[1:])
    args = (circ, boxes, w.beam_angles, 0.51, 5.0)
    r64, r32 = ray_cast(x, y, yaw, *args), ray_cast(x, y, yaw, *args, np.float32)
    assert r32.dtype == np.float32 and (r64 < 5.0).mean() > 0.05  # the scenes' bodies are in range
    assert np.abs(r32 - r64).max() < 1e-4


def test_every_shipped_weights_file_loads_and_drl_json_names_it():
    """Each .pt beside the policy (drl.pt, the stage-1/2 weights, drl-chain.pt) is a DuelingQNet state_dict
    whose provenance drl.json records."""
    import json

    from stack.policies.drl.policy import WEIGHTS, load_network
    from stack.train.drl import tensors

    folder = WEIGHTS.parent
    named = json.loads((folder / "drl.json").read_text())["weights"]
    files = sorted(p.name for p in folder.glob("*.pt"))
    assert {"drl.pt", "drl-chain.pt"} <= set(files) and set(files) <= set(named)
    for f in files:
        net = load_network(folder / f)
        o = DrlWorld(1, 1, seed=0).observe()
        assert net(*tensors({k: v[0] for k, v in o.items()}, torch)).shape == (1, 15)
