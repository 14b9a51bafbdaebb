"""Bai 2022 Fig. 8 for a chain of ``stack-train drl`` runs: average reward per 50 episodes, one run after the other.

  python bench/drl_fig8.py runs/drl-s1 runs/drl-s1b runs/drl-s1e runs/drl-s1f runs/drl-s2b --out docs/figures/bai-fig8-reward.png

Reads each RUN/drl.json (its ``curve``: one entry per episode) and draws the runs end to end, stage 1 in one
colour and stage 2 in another, with the run names at their starts; prints per run its episodes, wall time and
the success rate of its last 500 episodes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="run folders written by stack-train drl --out")
    ap.add_argument("--out", type=Path, default=Path("runs/bai-fig8-reward.png"))
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.8))
    start, total_wall = 0, 0.0
    for run in a.runs:
        f = run / "drl.json"
        if not f.exists():
            print(f"{f}: no such file (a stack-train drl --out folder?)", file=sys.stderr)
            return 2
        d = json.loads(f.read_text())
        ret = np.array([c["return"] for c in d["curve"]], float)
        k = np.arange(len(ret)) // 50
        means = np.bincount(k, ret) / np.bincount(k)
        x = start + (np.arange(len(means)) + 1) * 50
        stage = d["job"]["stage"]
        ax.plot(x, means, color="tab:blue" if stage == 1 else "tab:orange", label=f"stage {stage}")
        ax.axvline(start, color="0.8", lw=0.8)
        ax.text(start, float(means.min()), f" {run.name}", fontsize=7, va="bottom", rotation=90)
        last = d["curve"][-500:]
        succ = np.mean([c["outcome"] == "arrived" for c in last])
        print(f"{run}: stage {stage}, {len(ret)} episodes, {d['wall_s']:.0f} s, success over the last {len(last)}: {succ:.2f}")
        total_wall += d["wall_s"]
        start += len(ret)
    h, lab = ax.get_legend_handles_labels()
    uniq = dict(zip(lab, h))
    ax.legend(uniq.values(), uniq.keys(), loc="lower right")
    ax.set_xlabel("episode (runs end to end)")
    ax.set_ylabel("average reward (50 episodes)")
    ax.set_title("stack-train drl, Bai 2022 Fig. 8")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=110)
    print(f"total wall {total_wall:.0f} s; wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
