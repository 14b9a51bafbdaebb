"""Lean agents (issue 21): what an agent process imports and holds, and that the lean paths compute what the
heavy ones did (the DRL network without torch). The EKF is filterpy's class without the rest of filterpy
(stack/estimation/_filterpy.py; tests/test_estimation.py)."""

from __future__ import annotations

import copy
import functools
from pathlib import Path

import numpy as np


# --- the DRL network without torch ----------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _nets():
    import torch

    from stack.policies.drl.numpy_net import NumpyQNet, load_npz
    from stack.policies.drl.policy import WEIGHTS, WEIGHTS_NPZ, load_network

    torch.set_num_threads(1)  # as in an agent process
    net = load_network(WEIGHTS)
    net.double64 = copy.deepcopy(net).double()
    return torch, net, NumpyQNet(load_npz(WEIGHTS_NPZ)), NumpyQNet(load_npz(WEIGHTS_NPZ), dtype=np.float64)


F32 = 3e-5
"""Both float32 passes lie within this of the exact network (float64) and of each other. Torch's own float32
pass is up to 1.6e-5 from its float64 pass on these inputs (|Q| up to 27; sums over 1376 conv features), so
no float32 pass can promise 1e-6 of torch's; in float64 the two agree to 1e-10 (measured 2.5e-14)."""


def _assert_equal(torch, net, np32, np64, s, g, nb):
    """numpy float64 = torch float64 (the same function); numpy float32 within float32 rounding of both."""
    ts = [torch.from_numpy(np.ascontiguousarray(a, np.float32)) for a in (s, g, nb)]
    with torch.inference_mode():
        q32 = net(*ts).numpy()
        q64 = net.double64(*[t.double() for t in ts]).numpy()
    got32, got64 = np32(s, g, nb), np64(s, g, nb)
    assert got32.dtype == np.float32 and got32.shape == q32.shape
    assert np.abs(got64 - q64).max() <= 1e-10
    assert np.abs(got32 - q32).max() <= F32 and np.abs(got32 - q64).max() <= F32, (np.abs(got32 - q32).max(), np.abs(q32 - q64).max())
    assert (got32.argmax(1) == q32.argmax(1)).mean() >= 0.99  # ties within float32 rounding may break either way
    return np.abs(got32 - q32).max()


def test_the_numpy_network_gives_torchs_q_values_on_random_inputs():
    torch, net, np32, np64 = _nets()
    rng = np.random.default_rng(0)
    for n_nb in (0, 1, 3, 31):  # no neighbour, one, a few, a 32-robot fleet
        s = rng.uniform(0, 1, (32, 3, 180)).astype(np.float32)
        g = rng.uniform(-1, 1, (32, 4)).astype(np.float32)
        nb = rng.uniform(-1, 1, (32, n_nb, 2)).astype(np.float32)
        _assert_equal(torch, net, np32, np64, s, g, nb)


def test_the_numpy_network_gives_torchs_q_values_on_real_observations():
    """The observations of four-robot scenes of the training world (stage 2), driven greedily by the network."""
    from stack.policies.drl.observation import ACTIONS
    from stack.train.drlworld import DrlWorld, WorldConfig, held_out_scenes

    torch, net, np32, np64 = _nets()
    w = DrlWorld(4, 2, seed=5, cfg=WorldConfig(max_steps=60))
    w.reset(np.ones(4, bool), held_out_scenes(4, 2, seed=7))
    seen = 0
    for _ in range(40):
        o = {k: v.reshape((4 * w.R,) + v.shape[2:]) for k, v in w.observe().items()}
        for k in range(1, 4):  # rows by neighbour count (the numpy pass takes unpadded sequences)
            rows = o["n_nb"] == k
            if rows.any():
                _assert_equal(torch, net, np32, np64, o["scans"][rows], o["gv"][rows], o["nb"][rows][:, :k])
                seen += int(rows.sum())
        w.step(np32(o["scans"], o["gv"], o["nb"][:, :0]).argmax(1).reshape(4, w.R), ACTIONS)
    assert seen > 100


def test_the_shipped_npz_is_the_export_of_the_shipped_weights(tmp_path):
    from stack.policies.drl.numpy_net import export_npz, load_npz
    from stack.policies.drl.policy import WEIGHTS, WEIGHTS_NPZ, load_network

    out = export_npz(load_network(WEIGHTS).state_dict(), tmp_path / "drl.npz")
    shipped, fresh = load_npz(WEIGHTS_NPZ), load_npz(out)
    assert shipped.keys() == fresh.keys() and all(np.array_equal(shipped[k], fresh[k]) for k in shipped)


def test_both_runtimes_drive_alike_and_load_either_file(tmp_path):
    from stack.policies.base import Observation
    from stack.policies.drl.config import DrlConfig
    from stack.policies.drl.policy import WEIGHTS, WEIGHTS_NPZ, DrlPolicy

    rng = np.random.default_rng(1)
    pols = [DrlPolicy(cfg=DrlConfig(runtime="numpy")), DrlPolicy(cfg=DrlConfig(runtime="torch")),
            DrlPolicy(WEIGHTS, cfg=DrlConfig(runtime="numpy")), DrlPolicy(WEIGHTS_NPZ, cfg=DrlConfig(runtime="torch"))]
    assert [p.torch for p in pols] == [False, True, False, True]
    for _ in range(50):
        obs = Observation(d_g=rng.uniform(0, 8), alpha_g=rng.uniform(-3, 3), v=rng.choice([0, 0.5, 1.0]), w=0.0,
                          neighbours=rng.uniform(0, 1, (int(rng.integers(0, 4)), 2)) * [10, 3],
                          scans=rng.uniform(0.5, 5.0, (3, 180)))
        acts = {p.act(obs) for p in pols}
        assert len(acts) == 1, acts
        assert np.abs(pols[0].last_q - pols[1].last_q).max() <= F32
    bad = tmp_path / "bad.npz"
    np.savez(bad, w=np.zeros(3))
    import pytest

    with pytest.raises(ValueError, match=r"bad\.npz: not DuelingQNet weights"):
        DrlPolicy(bad, cfg=DrlConfig())


# --- what an agent process imports and holds -----------------------------------------------------------
def test_a_drl_agent_with_the_numpy_runtime_imports_no_torch():
    """The agent's modules and its control step with the drl policy (torch installed here, nothing blocked)."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import sys
        import numpy as np
        import stack.agents.cli
        from stack.agents.step import OdomSample, StepInputs, StepPipeline
        from stack.comm.messages import Scan
        from stack.scenario import load_scenario, with_overrides
        sc = with_overrides(load_scenario("scenarios/four-robot-obstacles.yaml"), policy="drl")
        pipe = StepPipeline(sc, 1)
        assert pipe.policy.name == "drl" and not pipe.policy.torch
        scan = Scan(id=1, step=0, stamp=0.0, angle_min=-np.pi / 2, angle_increment=np.pi / 179, range_max=5.0,
                    ranges=[5.0] * 180)
        for k in range(5):
            t = 0.1 * k
            pipe.step(StepInputs(step=k, t=t, t_run=t, now=t, odometry=(OdomSample(t=t, v=0.0, w=0.0),), scan=scan, scan_t=t))
        from stack.policies.base import Observation
        pipe.policy.act(Observation(d_g=4.0, alpha_g=0.2, v=0.5, w=0.0, neighbours=np.array([[3.0, 1.0]]),
                                    scans=np.full((3, 180), 2.0)))  # the network itself, whatever the situation
        heavy = sorted(({m.split(".")[0] for m in sys.modules} & {"torch", "pybullet", "matplotlib"})
                       | ({"scipy.stats", "scipy.ndimage", "filterpy.kalman.UKF"} & set(sys.modules)))
        print(heavy, pipe.policy.last_q is not None)
    """)
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=Path(__file__).resolve().parents[1])
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["[]", "True"], p.stdout


def test_a_drl_fleet_runs_numpy_agents_without_torch(tmp_path):
    """A lock-step drl fleet (the numpy runtime, the default): every agent drives, none maps libtorch, each stays
    under the issue's 120 MB (PSS) per DRL agent. (A torch agent is not in it: importing torch takes over 30 s
    on a loaded 2-core machine, past the agents' no-sensor timeout; the torch runtime is checked above.)"""
    from conftest import scenario_dict

    from stack.fleet.orchestrator import Fleet, FleetConfig
    from stack.fleet.procmem import Sampler
    from stack.fleet.procs import Proc
    from stack.scenario import parse_scenario

    d = scenario_dict(duration=4.0)
    d["robot"]["policy"] = "drl"
    sc = parse_scenario(d, "lean.yaml")
    with Sampler(Proc, period_s=0.3, libs=True) as s:
        code, rep = Fleet(FleetConfig(scenario=sc, out=tmp_path / "out", progress=False, plots=False), spawn=s).run()
    assert rep["crashed"] == [] and set(rep["policies"].values()) == {"drl"}, (code, rep["crashed"])
    torch_libs = {name for name, libs in s.libs.items() if any(lib.startswith("libtorch") for lib in libs)}
    assert torch_libs == set() and len(s.libs) == 6, (torch_libs, sorted(s.libs))  # router, world, 4 agents
    peaks = s.peaks()
    for rid in range(4):
        assert 20 < peaks[f"agent {rid}"]["pss"] < 120, peaks[f"agent {rid}"]
    z = np.load(tmp_path / "out" / "truth.npz")
    assert (np.abs(z["v"]).max(axis=0) > 0.1).all()  # every robot moved
