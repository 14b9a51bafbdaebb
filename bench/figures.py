"""Every figure in the documentation, made again from runs of this stack (``make figures``).

  python bench/figures.py --list                 # which command makes which figure, and about how long it takes
  python bench/figures.py                        # all of them (hours: the held-out tables and the DRL chain)
  python bench/figures.py --only replay-six-robot.gif mixed-reality-tracks.png

One record per command (:data:`FIGURES`): what it runs, from the repository's root, and which of its outputs
become which files under ``docs/``. A test checks the registry against the folders (every figure in
``docs/figures`` and every picture beside the pages is made by exactly one record), so a picture never shows
an older stack without a command to make it again. Each record's command is the one its page quotes.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
FLEET = [PY, "-m", "stack.fleet"]
TRAIN = [PY, "-m", "stack.train"]
SWEEP_SCENES = "runs/figures/sweep-scenarios"


@dataclass(frozen=True)
class Figure:
    """One command and the figures it makes."""

    name: str
    """What the figures show (for ``--list`` and the progress line)."""
    commands: tuple[tuple[str, ...], ...]
    """Run in order from the repository's root."""
    copies: dict[str, str] = field(default_factory=dict)
    """A command's output (relative to the root) -> the figure under ``docs/`` it becomes."""
    minutes: float = 1.0
    """About how long it takes on a 2-core machine."""


def _sweep(param: str, values: str, seeds: int, policies: str | None, out: str) -> tuple[str, ...]:
    extra = ("--policies", policies) if policies else ()
    return (*FLEET, "bench", "--sweep", f"{param}={values}", "--seeds", str(seeds), "--scenarios", SWEEP_SCENES,
            "--jobs", "2", "--out", out, *extra)


_SCENES = (PY, "-c", "import shutil, pathlib; p = pathlib.Path('" + SWEEP_SCENES + "'); p.mkdir(parents=True, "
           "exist_ok=True); [shutil.copy(f'scenarios/{n}.yaml', p) for n in ('four-robot-diamond', "
           "'four-robot-obstacles')]")

FIGURES: tuple[Figure, ...] = (
    Figure("a six-robot run, animated (docs/visualisation.md)",
           ((*FLEET, "run", "scenarios/six-robot.yaml", "--policy", "pid", "--duration", "60", "--out",
             "runs/figures/six-robot"),),
           {"runs/figures/six-robot/replay.gif": "figures/replay-six-robot.gif"}, 1),
    Figure("a recording and a live run in Lichtblick (docs/visualisation.md)",
           ((PY, "-m", "pytest", "-q", "tests/test_viewer.py"),),
           {"runs/figures/shots/lichtblick-recording.png": "figures/lichtblick-recording.png",
            "runs/figures/shots/lichtblick-live.png": "figures/lichtblick-live.png"}, 2),
    Figure("comm sweeps of aina, qlearn and pid (docs/sweeps.md)",
           (_SCENES, _sweep("loss", "0,0.1,0.2,0.3,0.4,0.5", 3, "pid,aina,qlearn", "runs/figures/sweeps/loss"),
            _sweep("latency_ms", "0,50,100,200,500", 3, "pid,aina,qlearn", "runs/figures/sweeps/latency_ms"),
            _sweep("burst", "0.1,0.2,0.3", 3, "pid,aina,qlearn", "runs/figures/sweeps/burst")),
           {"runs/figures/sweeps/loss/loss_sweep.png": "loss_sweep.png",
            "runs/figures/sweeps/latency_ms/latency_ms_sweep.png": "latency_ms_sweep.png",
            "runs/figures/sweeps/burst/burst_sweep.png": "burst_sweep.png"}, 40),
    Figure("comm sweeps of drl (docs/sweeps.md)",
           (_SCENES, _sweep("loss", "0,0.1,0.2,0.3,0.4,0.5", 3, "drl", "runs/figures/sweeps-drl/loss"),
            _sweep("burst", "0.1,0.2,0.3", 2, "drl", "runs/figures/sweeps-drl/burst"),
            _sweep("latency_ms", "0,100,500", 2, "drl", "runs/figures/sweeps-drl/latency_ms")),
           {"runs/figures/sweeps-drl/loss/loss_sweep.png": "figures/drl_loss_sweep.png",
            "runs/figures/sweeps-drl/burst/burst_sweep.png": "figures/drl_burst_sweep.png",
            "runs/figures/sweeps-drl/latency_ms/latency_ms_sweep.png": "figures/drl_latency_ms_sweep.png"}, 30),
    Figure("Bai's network in the fleet, three layouts (docs/policy-drl.md)",
           ((PY, "bench/drl_fleet.py", "--seeds", "3", "--out", "runs/figures/drl-fleet", "--figures", "docs/figures"),),
           {}, 10),
    Figure("held-out success per density, every policy (docs/heldout.md)",
           ((PY, "bench/heldout.py", "--courses", "34", "--arrival", "34", "--first-seed", "1000102", "--jobs", "2",
             "--out", "runs/figures/heldout"),),
           {"runs/figures/heldout/heldout_success.png": "figures/heldout_success.png"}, 300),
    Figure("held-out success of drl and the network alone (docs/heldout.md)",
           ((PY, "bench/heldout.py", "--courses", "34", "--arrival", "0", "--first-seed", "1000170", "--policies",
             "drl,drl-alone", "--jobs", "2", "--out", "runs/figures/heldout-alone"),),
           {"runs/figures/heldout-alone/heldout_success.png": "figures/heldout_success_alone.png"}, 120),
    Figure("held-out success on the whole chain's weights (docs/heldout.md)",
           ((PY, "bench/heldout.py", "--courses", "20", "--arrival", "0", "--first-seed", "1000204", "--policies",
             "drl,drl-alone", "--drl-weights", "stack/policies/drl/weights/drl-chain.pt", "--jobs", "2", "--out",
             "runs/figures/heldout-chain"),),
           {"runs/figures/heldout-chain/heldout_success.png": "figures/heldout_success_chain.png"}, 80),
    Figure("held-out success at high density with the brake and plans beside the step (docs/heldout.md)",
           ((PY, "bench/heldout.py", "--courses", "34", "--arrival", "0", "--densities", "high", "--first-seed",
             "1000224", "--policies", "drl,drl-alone,aina,qlearn", "--jobs", "2", "--out", "runs/figures/heldout-high"),),
           {"runs/figures/heldout-high/heldout_success.png": "figures/heldout_success_high.png"}, 32),
    Figure("the DRL training chain drawn end to end, and its stage-3 weights held out (docs/policy-drl.md, "
           "docs/heldout.md)",
           (("bash", "bench/drl_chain.sh", "runs/figures/drl-chain"),
            (PY, "bench/drl_fig8.py", *(f"runs/figures/drl-chain/{r}" for r in ("drl-s1", "drl-s1b", "drl-s1e",
                                                                                "drl-s1f", "drl-s2b")),
             "--out", "runs/figures/bai-fig8-reward.png"),
            (PY, "bench/heldout.py", "--courses", "34", "--arrival", "0", "--first-seed", "1000136", "--policies",
             "drl", "--drl-weights", "runs/figures/drl-chain/drl-s3j/drl.pt", "--jobs", "2", "--out",
             "runs/figures/heldout-s3")),
           {"runs/figures/bai-fig8-reward.png": "figures/bai-fig8-reward.png",
            "runs/figures/heldout-s3/heldout_success.png": "figures/heldout_success_stage3.png"}, 160),
    Figure("the first stage-3 run's reward (docs/policy-drl.md, \"Stage 3\")",
           ((*TRAIN, "drl", "--stage", "3", "--init", "stack/policies/drl/weights/drl-stage2.pt", "--episodes", "6000",
             "--eps-start", "0.2", "--eps-end", "0.02", "--eps-fraction", "0.5", "--lr", "2.5e-4", "--seed", "11",
             "--envs", "32", "--max-steps", "250", "--n-step", "3", "--target-every", "100", "--time-penalty", "0.01",
             "--stall-steps", "30", "--max-minutes", "48", "--out", "runs/figures/drl-s3"),),
           {"runs/figures/drl-s3/reward.png": "figures/drl-stage3-reward.png"}, 50),
    Figure("Chang's PSO, phase 1 and phase 2 (docs/policy-fuzzy.md)",
           ((*TRAIN, "fuzzy", "--phase", "1", "--particles", "20", "--iterations", "200", "--seed", "1", "--out",
             "runs/figures/fuzzy-p1"),
            (*TRAIN, "fuzzy", "--phase", "2", "--coordinator", "flc", "--init", "hand", "--particles", "8",
             "--iterations", "6", "--max-steps", "1600", "--out", "runs/figures/fuzzy-p2")),
           {"runs/figures/fuzzy-p1/fig9-phase1.png": "figures/chang-fig9-phase1.png",
            "runs/figures/fuzzy-p2/fig9-phase2.png": "figures/chang-fig9-phase2.png"}, 4),
    Figure("a real Jackal and three simulated robots (docs/mixed-reality.md)",
           ((PY, "bench/mixed_bench.py", "--seeds", "2", "--out", "runs/figures/mixed"),),
           {"runs/figures/mixed/mixed_tracks.png": "figures/mixed-reality-tracks.png"}, 10),
)
"""Every figure of the documentation; ``bench/drl_fleet.py --figures`` writes its ``bai-drl-*`` plots itself."""

DRL_FLEET = tuple(f"figures/bai-drl-{s}-{k}.png" for s in ("bai-case2", "four-robot-obstacles", "six-robot")
                  for k in ("trajectories", "distances"))
"""What ``bench/drl_fleet.py --figures docs/figures`` writes."""


def made() -> dict[str, str]:
    """Each figure under ``docs/`` -> the record that makes it."""
    out: dict[str, str] = {}
    for fig in FIGURES:
        for dst in (*fig.copies.values(), *(DRL_FLEET if "drl_fleet.py" in str(fig.commands) else ())):
            if dst in out:
                raise ValueError(f"{dst} is made by two records: {out[dst]!r} and {fig.name!r}")
            out[dst] = fig.name
    return out


def run(fig: Figure) -> None:
    env_shots = {"STACK_SHOTS": str(ROOT / "runs/figures/shots")}
    for cmd in fig.commands:
        print("$", " ".join(cmd), flush=True)
        subprocess.run(cmd, cwd=ROOT, check=True, env={**__import__("os").environ, **env_shots})
    for src, dst in fig.copies.items():
        shutil.copy(ROOT / src, ROOT / "docs" / dst)
        print(f"docs/{dst} <- {src}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--list", action="store_true", help="say which command makes which figure and stop")
    ap.add_argument("--only", nargs="+", default=None, metavar="FIGURE",
                    help="the records that make these figures (names under docs/, e.g. replay-six-robot.gif)")
    a = ap.parse_args(argv)
    figs = FIGURES
    if a.only:
        wanted = {Path(n).name for n in a.only}
        figs = tuple(f for f in FIGURES if wanted & {Path(d).name for d in f.copies.values()})
        if not figs:
            print(f"figures.py: no record makes {sorted(wanted)} (see --list)", file=sys.stderr)
            return 2
    if a.list:
        for f in figs:
            print(f"{f.name} (about {f.minutes:g} min):")
            for cmd in f.commands:
                print("   ", " ".join(c.replace(PY, "python") for c in cmd))
        return 0
    from tqdm import tqdm

    for f in tqdm(figs, desc="figures", unit="record"):
        run(f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
