"""Build policies from a robot's config (duck-typed: policies import nothing of ours above them)."""

from __future__ import annotations

from .pid import PidGains, PidPolicy


def make_pid(robot, **_) -> PidPolicy:
    p = robot.pid
    v_cap = robot.v_max * (p.v_cruise if robot.role == "leader" else 1.0)  # the leader cruises
    return PidPolicy(PidGains(k_v=p.k_v, k_w=p.k_w, k_i=p.k_i, k_d=p.k_d, v_cap=v_cap))


def make_aina(robot, *, seed: int = 0, **_):
    from .aina import AinaPolicy

    return AinaPolicy(robot.aina, role=robot.role or "leader", radius=robot.radius, v_max=robot.v_max,
                      lidar_fov=robot.lidar.fov, lidar_range=robot.lidar.range, seed=seed)


def make_qlearn(robot, *, seed: int = 0, **kw):
    from .qlearn import make_qlearn as make

    return make(robot, seed=seed, **kw)


def make_fuzzy(robot, *, seed: int = 0, **kw):
    from .fuzzy import make_fuzzy as make

    return make(robot, seed=seed, **kw)


def make_fuzzy_lstm(robot, *, seed: int = 0, **kw):
    from .fuzzy import make_fuzzy_lstm as make

    return make(robot, seed=seed, **kw)


def make_drl(robot, *, seed: int = 0, **kw):
    from .drl.policy import make_drl as make

    return make(robot, seed=seed, **kw)
