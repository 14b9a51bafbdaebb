"""Chang 2020 PSO training (eq. 17-18): phase 1 the left BF controller, phase 2 each MRC.

Examples:
  stack-train fuzzy --phase 1 --out runs/fuzzy-p1 --ship
  stack-train fuzzy --phase 2 --coordinator both --out runs/fuzzy-p2 --ship

Phase 1 (section "Training Phase 1"): a particle is a whole 10-rule left BF controller (centres,
widths, consequents: 90 numbers). The robot drives at a constant 0.4 m/s with the object on its
left (``fuzzyworld.phase1_world``, Fig. 6 in spirit) until eq. (19) is violated; the fitness is
eq. (20), 1 / T_control, and a controller that lasts T_suc = 4000 steps is a success (the search
stops there). Eq. (19) is read as min(L5..L8) > D_min and min(L5..L8) <= D_max (D_min 0.5, D_max
1.5 m): with eight equal sectors over 180 deg the printed "L5 <= D_max" (L5 looks 0-22.5 deg left
of the heading) would need the robot within 1.5 sin 22.5 deg = 0.57 m of a straight wall, a band
of 7 cm above D_min; the paper's stated purpose is "prevents the robot from moving too far from
the object".

Phase 2 (section "Training Phase 2"): a particle is FLC_SR (5 rules x (5 + 5 + 2) = 60 numbers)
or the LSTM (62 weights, biases fixed at 0.5); three robots with the phase-1 BF controller drive
to goals around the target (``fuzzyworld.phase2_task``, Fig. 7 in spirit: 30.4, 39.5, 43.8 m).
The paper trains on that one task. Trained so, both MRCs fitted its timing (spread 1 step there)
and did worse on the test scenarios than the hand-set ones (spread about 100 steps, and the
LSTM's robots touched), so the fitness here is the mean of eq. (21) over two fields
(``fuzzyworld.phase2_tasks``: Fig. 7's and a second three-robot one, 22 / 35 / 47 m); neither
is a test scenario.
**Eq. (21)-(23) as we read them.** As printed f_2 = |T_rank1 - T_rankn| / 2 = f_1 / 2, so eq. (21)
would be 10.05 f_1, with nothing that makes the robots "move as fast as possible". Table 1 gives
the reading: f_phase2 = 57.73 with "f_1" = 532.0 and "f_2" = 0.41, and 0.1 x 532.0 + 10 x 0.41 =
57.3: the table's f_1 is the time to complete the task and its f_2 the arrival spread, weighted
0.1 and 10. So f_phase2 = 10 |T_rank1 - T_rankn| + 0.1 T_complete (steps), T_complete the last
arrival. A run where a robot does not arrive in ``max_steps`` counts as spread = completion =
max_steps (counting only its arrival as max_steps let a swarm find that "nobody arrives" scores a
spread of 0); a collision adds 1000 per collision.

Fitness evaluations run in the numpy world (:mod:`.fuzzyworld`) over ``--workers`` processes.
Writes OUT/phase1.json or OUT/phase2-<coordinator>.json (best parameters, fitness, curve) and the
best-so-far curves as OUT/fig9-*.png (Fig. 9); ``--ship`` merges the result into the package's
``stack/policies/fuzzy/params/chang2020.json``, which ``--policy fuzzy`` / ``fuzzy-lstm`` load.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from functools import partial
from pathlib import Path

import numpy as np

from ..argtypes import positive_int
from ..models.kinematics import arc_step

T_SUC = 4000  # phase 1: steps of a successful BF controller
V_BF = 0.4  # phase 1: constant speed [m/s]
D_MIN, D_MAX = 0.5, 1.5  # eq. (19)
BF_RULES = 10
SR_RULES = 5


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--phase", type=int, choices=(1, 2), required=True, help="1: left BF controller; 2: the MRC(s)")
    p.add_argument("--coordinator", choices=("flc", "lstm", "both"), default="both", help="phase 2: which MRC")
    p.add_argument("--particles", type=positive_int, default=20)
    p.add_argument("--iterations", type=positive_int, default=None, help="default 200 (phase 1), 50 (phase 2)")
    p.add_argument("--workers", type=positive_int, default=max(1, min(2, mp.cpu_count())))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--init", choices=("random", "hand", "current"), default=None,
                   help="start the swarm at random (phase 1 default), around the hand-set parameters, or around "
                        "the shipped ones (phase 2 default)")
    p.add_argument("--max-steps", type=positive_int, default=2500, help="phase 2: step limit of one run")
    p.add_argument("--out", type=Path, default=Path("runs/fuzzy"))
    p.add_argument("--ship", action="store_true", help="write the result into the package's params/chang2020.json")
    p.add_argument("--no-progress", action="store_true")


# -- fitness functions (module level: picklable for the pool) -------------------------------------
def phase1_fitness(vec: np.ndarray) -> float:
    """Eq. (20): 1 / T_control of one trial of left BF at 0.4 m/s (constraints eq. 19)."""
    from ..policies.fuzzy.rbc import BoundaryFollower, sectors
    from ..policies.fuzzy.tsk import TSK
    from .fuzzyworld import SimConfig, phase1_start, phase1_world, sectors_world

    bf = BoundaryFollower(TSK.from_vector(vec, BF_RULES, 4, 1))
    world, cfg = phase1_world(), SimConfig()
    x, y, th = phase1_start()
    for k in range(T_SUC):
        L = sectors(sectors_world(x, y, th, world, cfg), cfg.fov, cfg.range_max)
        left = L[4:].min()
        if not (left > D_MIN and left <= D_MAX):
            return 1.0 / max(k, 1)
        w = max(-cfg.w_max, min(cfg.w_max, bf.left(L) / 1.0))  # turn_time 1 s, as the policy
        x, y, th = arc_step(x, y, th, V_BF, w, cfg.dt)  # the exact arc of every other world (stack.models)
    return 1.0 / T_SUC


def phase2_fitness(vec: np.ndarray, coordinator: str, bf_left: dict, max_steps: int, seed: int = 0) -> float:
    return phase2_score(vec, coordinator, bf_left, max_steps, seed)[0]


def phase2_score(vec, coordinator: str, bf_left: dict, max_steps: int, seed: int = 0):
    """(f_phase2, spread, completion, collisions) on the phase-2 task (eq. 21-23 as read above)."""
    from ..policies.fuzzy.mrc import LstmWeights
    from ..policies.fuzzy.policy import FuzzyConfig, FuzzyPolicy, load_params
    from ..policies.fuzzy.tsk import TSK
    from .fuzzyworld import SimConfig, phase2_tasks, run

    params = load_params()
    params["bf_left"] = bf_left
    if coordinator == "flc":
        params["flc_sr"] = TSK.from_vector(vec, SR_RULES, 5, 2).to_dict()
    else:
        params["lstm"] = LstmWeights.from_vector(vec).to_dict()
    fs, spreads, completes, cols = [], [], [], 0
    for world, robots in phase2_tasks():
        pols = [FuzzyPolicy(FuzzyConfig(coordinator=coordinator), params) for _ in robots]
        r = run(world, robots, pols, SimConfig(max_steps=max_steps, noise_std=0.02), seed=seed)
        arr = [a if a is not None else max_steps for a in r.arrivals]
        # a robot that never arrives counts as the worst spread (else "nobody arrives" scores spread 0)
        spread = max_steps if None in r.arrivals else max(arr) - min(arr)
        complete = max(arr)
        c = r.collisions_robot + r.collisions_obstacle
        fs.append(10.0 * spread + 0.1 * complete + 1000.0 * c)
        spreads.append(spread)
        completes.append(complete)
        cols += c
    return float(np.mean(fs)), spreads, completes, cols


def _bounds_bf():
    n = BF_RULES * 4
    lo = np.concatenate([np.full(n, 0.3), np.full(n, 0.1), np.full(BF_RULES, -3.14)])
    hi = np.concatenate([np.full(n, 5.0), np.full(n, 10.0), np.full(BF_RULES, 3.14)])
    return lo, hi


def _bounds_sr():
    n = SR_RULES * 5
    lo = np.concatenate([np.full(n, 0.0), np.full(n, 0.02), np.full(SR_RULES * 2, 0.5)])
    hi = np.concatenate([np.full(n, 1.2), np.full(n, 1.0), np.full(SR_RULES * 2, 1.5)])
    return lo, hi


def _bounds_lstm():
    from ..policies.fuzzy.mrc import LstmWeights

    return np.full(LstmWeights.N_PARAMS, -4.0), np.full(LstmWeights.N_PARAMS, 4.0)


def _plot_curve(curves: dict[str, list[float]], path: Path, ylabel: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, c in curves.items():
        ax.plot(range(len(c)), c, marker=".", label=name)
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    ax.set_title("PSO best-so-far fitness (cf. Chang 2020 Fig. 9)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _optimise(fitness, lo, hi, cfg, *, seed, init, workers, progress, desc):
    from tqdm import tqdm

    from ..policies.fuzzy.pso import pso

    bar = tqdm(total=cfg.iterations + 1, desc=desc, disable=not progress, unit="it")

    def cb(it, best):
        bar.update(1)
        bar.set_postfix(best=f"{best:.5g}")

    if workers > 1:
        with mp.get_context("fork").Pool(workers) as pool:
            res = pso(fitness, lo, hi, cfg, seed=seed, init=init, evaluate=lambda f, xs: pool.map(f, xs), callback=cb)
    else:
        res = pso(fitness, lo, hi, cfg, seed=seed, init=init, callback=cb)
    bar.close()
    return res


def _ship(update: dict) -> Path:
    from ..policies.fuzzy.policy import PARAMS_FILE

    cur = json.loads(PARAMS_FILE.read_text()) if PARAMS_FILE.exists() else {}
    meta = cur.get("meta", {})
    meta.update(update.pop("meta", {}))
    cur.update(update)
    cur["meta"] = meta
    PARAMS_FILE.parent.mkdir(parents=True, exist_ok=True)
    PARAMS_FILE.write_text(json.dumps(cur, indent=1) + "\n")
    return PARAMS_FILE


def main(args) -> int:
    from ..policies.fuzzy.policy import load_params

    args.out.mkdir(parents=True, exist_ok=True)
    params = load_params()
    return _phase1(args, params) if args.phase == 1 else _phase2(args, params)


def _phase1(args, params: dict) -> int:
    """Phase 1: PSO over the left boundary follower's TSK (eq. 20 fitness); OUT/phase1.json, Fig. 9."""
    from ..policies.fuzzy.policy import hand_set_params
    from ..policies.fuzzy.pso import PsoConfig
    from ..policies.fuzzy.tsk import TSK

    out, t0 = args.out, time.perf_counter()
    start = hand_set_params() if args.init == "hand" else params
    init = TSK.from_dict(start["bf_left"]).to_vector() if args.init in ("hand", "current") else None
    lo, hi = _bounds_bf()
    cfg = PsoConfig(particles=args.particles, iterations=args.iterations or 200, target=1.0 / T_SUC)
    res = _optimise(phase1_fitness, lo, hi, cfg, seed=args.seed, init=init, workers=args.workers,
                    progress=not args.no_progress, desc="phase 1 (left BF)")
    ok = res.best_f <= 1.0 / T_SUC + 1e-12
    bf = TSK.from_vector(res.best, BF_RULES, 4, 1).to_dict()
    wall = time.perf_counter() - t0
    doc = {"phase": 1, "success": ok, "T_control": round(1.0 / res.best_f), "fitness": res.best_f,
           "iterations": len(res.curve) - 1, "evaluations": res.evaluations, "curve": res.curve,
           "wall_s": round(wall, 1), "init": args.init or "random", "seed": args.seed, "bf_left": bf}
    (out / "phase1.json").write_text(json.dumps(doc, indent=1) + "\n")
    _plot_curve({"left BF": res.curve}, out / "fig9-phase1.png", "f_phase1 = 1 / T_control")
    print(f"phase 1: {'success' if ok else 'no success'}: T_control {doc['T_control']} steps after "
          f"{doc['iterations']} iterations ({res.evaluations} evaluations) in {wall:.0f} s; {out / 'phase1.json'}")
    if args.ship:
        if ok:
            meta = f"PSO phase 1, seed {args.seed}: T_control {doc['T_control']} after {doc['iterations']} iterations"
            print(f"shipped: {_ship({'bf_left': bf, 'meta': {'bf_left': meta}})}")
        else:
            print("not shipped: no successful controller")
    return 0 if ok else 1


def _phase2(args, params: dict) -> int:
    """Phase 2: PSO over each coordinator (eq. 21 fitness); OUT/phase2-<c>.json each, Fig. 9."""
    from ..policies.fuzzy.policy import hand_set_params

    coords = ["flc", "lstm"] if args.coordinator == "both" else [args.coordinator]
    start = hand_set_params() if args.init == "hand" else params
    curves, update = {}, {"meta": {}}
    for c in coords:
        key, best, doc = _phase2_one(args, c, start, params["bf_left"])
        curves[{"flc": "fuzzy-logic-based MRC", "lstm": "recurrent-based MRC"}[c]] = doc["curve"]
        update[key] = best
        update["meta"][key] = (f"PSO phase 2, seed {args.seed}, {doc['iterations']} iterations x {args.particles} "
                               f"particles: mean f {doc['f_phase2']:.1f} (spread {doc['spread_steps']}, completion "
                               f"{doc['completion_steps']} steps) on the two training tasks")
    _plot_curve(curves, args.out / "fig9-phase2.png", "f_phase2 = 10 spread + 0.1 completion")
    if args.ship:
        print(f"shipped: {_ship(update)}")
    return 0


def _phase2_one(args, c: str, start: dict, bf_left: dict) -> tuple[str, dict, dict]:
    """One coordinator's phase 2 ("flc" or "lstm"): (params key, best params, the OUT/phase2-<c>.json document)."""
    from ..policies.fuzzy.mrc import LstmWeights
    from ..policies.fuzzy.pso import PsoConfig
    from ..policies.fuzzy.tsk import TSK

    t1, it = time.perf_counter(), args.iterations or 50
    if c == "flc":
        lo, hi = _bounds_sr()
        init = TSK.from_dict(start["flc_sr"]).to_vector()
    else:
        lo, hi = _bounds_lstm()
        init = LstmWeights.from_dict(start["lstm"]).to_vector()
    if args.init == "random":
        init = None
    fit = partial(phase2_fitness, coordinator=c, bf_left=bf_left, max_steps=args.max_steps, seed=args.seed)
    cfg = PsoConfig(particles=args.particles, iterations=it, init_spread=0.3)
    res = _optimise(fit, lo, hi, cfg, seed=args.seed, init=init, workers=args.workers, progress=not args.no_progress,
                    desc=f"phase 2 ({c})")
    f, spread, complete, cols = phase2_score(res.best, c, bf_left, args.max_steps, args.seed)
    wall = time.perf_counter() - t1
    best = (TSK.from_vector(res.best, SR_RULES, 5, 2).to_dict() if c == "flc"
            else LstmWeights.from_vector(res.best).to_dict())
    key = "flc_sr" if c == "flc" else "lstm"
    doc = {"phase": 2, "coordinator": c, "f_phase2": f, "spread_steps": spread, "completion_steps": complete,
           "collisions": cols, "iterations": it, "evaluations": res.evaluations, "curve": res.curve,
           "wall_s": round(wall, 1), "seed": args.seed, key: best}
    path = args.out / f"phase2-{c}.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"phase 2 ({c}): f_phase2 {f:.1f} (spread {spread} steps, completion {complete} steps per task, {cols} collisions) "
          f"after {it} iterations in {wall:.0f} s; {path}")
    return key, best, doc
