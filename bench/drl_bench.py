"""DRL policy (``--policy drl``, Bai 2022): act latency and the held-out evaluation.

Times ``DrlPolicy.act`` (normalisation + one forward pass of the Fig. 5 network, batch of one,
``torch.set_num_threads(1)`` as in every agent process) over a stream of changing
observations with 0-3 neighbours, and prints p50 / p99 / max in milliseconds (goal, issue 5:
p99 < 2 ms). Then runs the weights greedily on the held-out scenes of the training world
(:func:`stack.train.drl.evaluate`) and prints the success / collision / timeout rates (goal:
stage 1, 200 episodes: success >= 95 %, collisions <= 2 %).

    python bench/drl_bench.py --walls 0 --stage 1 2              # the shipped weights, the paper's scenes
    python bench/drl_bench.py --weights stack/policies/drl/weights/drl-stage1.pt --walls 0 --eval-seed 777
    python bench/drl_bench.py --no-shield --episodes 0            # act latency of the network alone

``act`` is timed with the action shield on (as ``--policy drl`` runs by default); the held-out
evaluation is the network alone (the training world's greedy runs).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stack.policies.base import Observation  # noqa: E402
from stack.policies.drl.config import DrlConfig  # noqa: E402
from stack.policies.drl.policy import WEIGHTS, DrlPolicy  # noqa: E402
from stack.train.drl import evaluate  # noqa: E402


def latency(policy: DrlPolicy, calls: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    obs = [Observation(d_g=float(rng.uniform(0, 10)), alpha_g=float(rng.uniform(-3, 3)), v=float(rng.uniform(0, 1)), w=float(rng.uniform(-1, 1)),
                       neighbours=np.sort(rng.uniform(0.5, 10, (k, 2)) * [1, 0.3], axis=0)[::-1], scans=rng.uniform(0.3, 5.0, (3, 180)))
           for k in rng.integers(0, 4, 64)]
    for o in obs[:10]:
        policy.act(o)  # warm-up
    ts = np.empty(calls)
    for i in range(calls):
        t0 = time.perf_counter()
        policy.act(obs[i % len(obs)])
        ts[i] = time.perf_counter() - t0
    ms = ts * 1e3
    return {"calls": calls, "p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", type=Path, default=WEIGHTS)
    ap.add_argument("--calls", type=int, default=5000)
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--stage", type=int, nargs="+", default=[1], choices=(1, 2))
    ap.add_argument("--epsilon", type=float, default=0.0, help="random-action chance in the evaluation (default 0: greedy)")
    ap.add_argument("--feasible", action="store_true", help="also check by flood fill that every stage-1 held-out scene is solvable")
    ap.add_argument("--walls", type=int, default=2, choices=range(0, 4), help="walls per held-out scene, 0..N (0: the paper's scenes)")
    ap.add_argument("--robots", type=int, default=4, help="stage 2: robots per scene (default 4)")
    ap.add_argument("--eval-seed", type=int, default=None, help="held-out seed (default: the training's HELD_OUT_SEED)")
    ap.add_argument("--no-shield", action="store_true", help="time act without the action shield")
    ap.add_argument("--json", type=Path, help="also write the numbers here")
    a = ap.parse_args(argv)
    from stack.train.drl import HELD_OUT_SEED

    seed = HELD_OUT_SEED if a.eval_seed is None else a.eval_seed
    policy = DrlPolicy(a.weights, cfg=DrlConfig(shield=not a.no_shield))  # sets torch threads to 1
    out = {"weights": str(a.weights), "shield": not a.no_shield, "act": latency(policy, a.calls)}
    lat = out["act"]
    print(f"act ({lat['calls']} calls, 1 thread, shield {'off' if a.no_shield else 'on'}): p50 {lat['p50_ms']:.3f} ms, p99 {lat['p99_ms']:.3f} ms, max {lat['max_ms']:.2f} ms")
    for st in a.stage:
        if a.episodes:
            t0 = time.perf_counter()
            ev = evaluate(policy.net, stage=st, episodes=a.episodes, epsilon=a.epsilon, max_walls=a.walls, robots=a.robots, seed=seed)
            out[f"stage{st}"] = ev
            print(f"held-out stage {st} ({ev['episodes']} episodes, seed {ev['seed']}): success {ev['success']:.1%}, "
                  f"collision {ev['collision']:.1%}, timeout {ev['timeout']:.1%} ({time.perf_counter() - t0:.0f} s)")
    if a.feasible:
        from stack.train.drlworld import held_out_scenes, reachable

        ok = [reachable(sc[0][0], sc[2][0], sc[3], sc[4]) for sc in held_out_scenes(a.episodes, 1, seed, a.walls)]
        out["feasible"] = int(sum(ok))
        print(f"stage-1 held-out scenes solvable (flood fill, clearance radius + 5 cm): {sum(ok)}/{len(ok)}")
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
