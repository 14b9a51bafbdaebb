"""Who drove into whom: the robot-robot contacts of ``drl`` fleet runs, each with what was driving the robot that moved.

  python bench/contacts.py runs/heldout-s3j/runs/drl-alone/*/*          # any run folders (stack-fleet run --out)

A contact is the first step at which two robots' centres come within two radii (+ 2 cm) of each other (the run's
``truth.npz``); the *mover* is the faster of the two half a second before. Its situation then (the decision layer's,
from the recording's ``/robot_<id>/state``) and what drove it over the last two seconds: ``network`` where every
command was one of Bai's 15 actions, ``tracker`` where none was (the PID: situation 1, or a planned detour's path
tracker), ``mixed`` otherwise. Prints one line per contact and the counts.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stack.policies.drl.observation import ACTIONS  # noqa: E402

BEFORE = 5  # steps (0.5 s): the mover is the faster robot then
WINDOW = 20  # steps (2 s): the commands judged


def situations(run: Path, ids) -> dict[int, dict[int, str]]:
    """robot id -> step -> situation, from the run's recording."""
    from mcap.reader import make_reader

    out: dict[int, dict[int, str]] = {i: {} for i in ids}
    with open(run / "run.mcap", "rb") as f:
        for _, _, m in make_reader(f).iter_messages(topics=[f"/robot_{i}/state" for i in ids]):
            s = json.loads(m.data)
            out[int(s["id"])][int(s["step"])] = s["situation"]
    return out


def driver(cmd: np.ndarray) -> str:
    """network, tracker or mixed: (k, 2) commands against the action table."""
    on = (np.abs(cmd[:, None, :] - ACTIONS[None]).max(axis=2) < 1e-3).any(axis=1)
    return "network" if on.all() else "tracker" if not on.any() else "mixed"


def contacts(run: Path, radius: float):
    """(t, mover, other, situation, driver) of each pair's first contact in ``run``."""
    z = np.load(run / "truth.npz")
    x, y, v, ids = z["x"], z["y"], z["v"], [int(i) for i in z["ids"]]
    cmd = np.stack([z["cmd_v"], z["cmd_w"]], -1)
    d = np.hypot(x[:, :, None] - x[:, None], y[:, :, None] - y[:, None])
    d[:, np.arange(len(ids)), np.arange(len(ids))] = np.inf
    first: dict[tuple[int, int], int] = {}
    for k, i, j in np.argwhere(d < 2 * radius + 0.02):
        first.setdefault((min(i, j), max(i, j)), int(k))
    sit = situations(run, ids) if first else {}
    for (i, j), k in sorted(first.items(), key=lambda p: p[1]):
        b = max(k - BEFORE, 0)
        m, o = (i, j) if v[b, i] >= v[b, j] else (j, i)
        steps = [s for s in sit[ids[m]] if s <= k]
        yield (float(z["t"][k]), ids[m], ids[o], sit[ids[m]][max(steps)] if steps else "?",
               driver(cmd[max(k - WINDOW, 0):k + 1, m]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="run folders (each with truth.npz and run.mcap)")
    ap.add_argument("--radius", type=float, default=0.5, help="the robots' radius [m] (default 0.5)")
    a = ap.parse_args(argv)
    counts: collections.Counter = collections.Counter()
    for run in a.runs:
        if not (run / "truth.npz").is_file():
            print(f"{run}: no truth.npz, skipped", file=sys.stderr)
            continue
        for t, m, o, s, drv in contacts(run, a.radius):
            counts[(s, drv)] += 1
            print(f"{run}: t={t:.1f} s robot {m} into robot {o}, {s}, {drv}")
    print(f"{sum(counts.values())} contacts:", ", ".join(f"{s} / {d} {n}" for (s, d), n in counts.most_common()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
