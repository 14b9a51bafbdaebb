"""Train briefly on the PettingZoo env, save weights ``--policy drl`` loads, fly them in a fleet (docs/env.md).

    python examples/train_env.py --steps 3000 --out runs/env-example            # from scratch
    python examples/train_env.py --steps 3000 --init stack/policies/drl/weights/drl.pt --out runs/env-ft

Writes OUT/drl.pt (a DuelingQNet state_dict), OUT/summary.json (training, held-out env evaluation, fleet
report summary) and OUT/<scenario>.yaml: a copy of the scenario whose ``robot.drl.weights`` is OUT/drl.pt,
then runs ``stack-fleet run OUT/<scenario>.yaml --policy drl --out OUT/fleet`` (``--no-fleet``: skip it).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import yaml

from stack.train.env import EnvConfig, FormationParallelEnv
from stack.train.envlearn import EnvLearnConfig, evaluate_on_env, train_on_env

HELD_OUT = 20_261  # env seeds of the evaluation (training uses --seed and its successors' scenes)


def scenario_with_weights(scenario: Path, weights: Path, out: Path) -> Path:
    """A copy of ``scenario`` in ``out`` whose robots' ``drl.weights`` is ``weights``."""
    data = yaml.safe_load(scenario.read_text())
    robot = data.setdefault("robot", {})
    robot["drl"] = dict(robot.get("drl") or {}) | {"weights": str(weights.resolve())}
    path = out / scenario.name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run_fleet(scenario: Path, out: Path, timeout: float = 600) -> dict | None:
    """``stack-fleet run SCENARIO --policy drl`` (one process per robot); its report, or None."""
    cmd = [sys.executable, "-m", "stack.fleet", "run", str(scenario), "--policy", "drl", "--out", str(out),
           "--no-progress", "--no-plots"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    rep = out / "report.json"
    if not rep.exists():
        print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
        return None
    return json.loads(rep.read_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=3000, help="environment steps to train")
    p.add_argument("--init", type=Path, default=None, help="start from these weights")
    p.add_argument("--robots", type=int, default=4, help="robots per random training scene (1: stage 1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=10, help="held-out env episodes (0: none)")
    p.add_argument("--scenario", type=Path, default=Path("scenarios/four-robot-diamond.yaml"))
    p.add_argument("--out", type=Path, default=Path("runs/env-example"))
    p.add_argument("--no-fleet", action="store_true", help="do not run the fleet")
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    env = FormationParallelEnv(EnvConfig(robots=a.robots, max_steps=250))
    weights = a.out / "drl.pt"
    # from scratch: explore widely; from weights: explore little and learn slowly, so as to keep what they know
    tune = {} if a.init is None else {"eps_start": 0.1, "eps_end": 0.02, "lr": 1e-4, "learn_start": 500}
    summary = {"train": train_on_env(env, EnvLearnConfig(steps=a.steps, init=a.init, seed=a.seed, **tune), weights)}
    if a.eval_episodes:
        from stack.policies.drl.policy import load_network

        summary["held_out_env"] = evaluate_on_env(load_network(weights), env, a.eval_episodes, HELD_OUT)
        print("held-out env episodes:", summary["held_out_env"])
    if not a.no_fleet:
        rep = run_fleet(scenario_with_weights(a.scenario, weights, a.out), a.out / "fleet")
        keys = ("success", "sim_time_s", "leader_time_to_goal_s", "collisions", "formation_error_rms_m", "end_reason")
        summary["fleet"] = {k: rep.get(k) for k in keys} if rep else None
        print("fleet:", summary["fleet"])
    (a.out / "summary.json").write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
