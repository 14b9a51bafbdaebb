"""Mixed reality against the all-simulated fleet: formation and goal error, judged on truth.

One scenario, a real leader and four simulated followers (``--followers``: a diamond and one behind it) over a
10 m course past a wall that stands in the site and a cylinder that
exists only in the world (``virtual``). Robot 0, the leader, is a Jackal:

- ``all simulated``: the fleet's world hosts its hardware-like Jackal like every other robot's base;
- ``mixed, <source>``: it is real (``embodiment: real``): a hardware-like Jackal in a stand-in site the fleet's
  world does not know (``stack.fleet.mixed``), its agent on ``--driver jackal`` as on the robot, its lidar merged
  with the virtual robots; the fleet's world places it from its estimate or from a motion-capture system
  (``--mocap`` in the site: ``PoseStamped`` at 10 / 30 / 100 Hz, 0 / 100 ms late).

Each run is judged on both worlds' truth (``stack.fleet.mixed.judge``): the followers where the fleet's world had
them, the leader where the site had it. Real time, one run per row and seed (``--seeds``). Writes
``OUT/mixed_bench.md`` and ``.json``::

    python bench/mixed_bench.py [--seeds 2] [--followers 4] [--out runs/mixed-bench]
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stack.comm.session import free_tcp_endpoint  # noqa: E402
from stack.fleet.mixed import formation_error_rms, run_mixed, site_namespace  # noqa: E402
from stack.scenario import parse_scenario  # noqa: E402

MOCAP_KEY = "vrpn_mocap/site_robot0/pose"
SOURCES = [None, (10, 0), (30, 0), (100, 0), (10, 100), (30, 100), (100, 100)]
"""None: the robot's estimate; (rate Hz, latency ms): a motion-capture system."""


FOLLOWERS = {1: ({"L": 2.0, "psi_deg": 135}, [-1.4, 1.4, 0.0]), 2: ({"L": 2.0, "psi_deg": 180}, [-2.0, 0.0, 0.0]),
             3: ({"L": 2.0, "psi_deg": -135}, [-1.4, -1.4, 0.0]), 4: ({"L": 4.0, "psi_deg": 180}, [-4.0, 0.0, 0.0])}
"""Follower id -> (its slot behind the leader, its start pose)."""


def scenario(seed: int, followers: int = 4) -> dict:
    ids = sorted(FOLLOWERS)[:followers]
    return {
        "name": "mixed-bench", "seed": seed, "dt": 0.1, "duration": 45.0,
        "world": {"obstacles": [{"type": "wall", "from": [-6, 4.5], "to": [14, 4.5], "thickness": 0.2},
                                {"type": "cylinder", "x": 5.0, "y": -3.2, "radius": 0.4, "virtual": True}]},
        "robot": {"radius": 0.3, "v_max": 0.8, "w_max": 1.5, "comm_range": 15.0,
                  "lidar": {"beams": 180, "fov_deg": 180, "range": 5.0}},
        "formation": {"leader": 0, "goal": [10.0, 0.0], "slots": {i: FOLLOWERS[i][0] for i in ids}},
        "robots": [{"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0], "driver": "jackal"},
                   *({"id": i, "role": "follower", "pose": FOLLOWERS[i][1]} for i in ids)],
        "success": {"goal_tolerance": 0.4, "max_time": 45.0, "no_collisions": True},
    }


def mixed(raw: dict, source) -> dict:
    raw = copy.deepcopy(raw)
    r0 = raw["robots"][0]
    r0.update(embodiment="real", jackal={"namespace": site_namespace(0)}, lidar={"virtual": True})
    if source is not None:
        r0["pose_source"] = {"key": MOCAP_KEY}
    return raw


def all_simulated(raw: dict, out: Path, endpoint: str) -> dict:
    """The same scenario with every robot in the fleet's world (its hardware-like Jackal hosted there)."""
    import subprocess

    import yaml

    out.mkdir(parents=True, exist_ok=True)
    path = out / "sim.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    subprocess.run([sys.executable, "-m", "stack.fleet", "run", str(path), "--realtime", "--connect", endpoint,
                    "--fleet", f"sim{raw['seed']}", "--out", str(out / "run"), "--no-progress", "--no-plots",
                    "--no-record"], check=False, capture_output=True, timeout=300, cwd=ROOT)
    rep = json.loads((out / "run" / "report.json").read_text())
    with np.load(out / "run" / "truth.npz") as z:
        truth = {k: z[k] for k in z.files}
    sc = parse_scenario(raw, str(path))
    goal = sc.formation.goal
    return {"report": rep, "judge": {"formation_error_rms_m": formation_error_rms(sc, truth),
                                     "goal_error_m": {"0": float(np.hypot(truth["x"][-1, 0] - goal[0],
                                                                          truth["y"][-1, 0] - goal[1]))},
                                     "clearance_m": {}, "estimate_error_rms_m": {}}}


def row(name: str, got: dict) -> dict:
    rep, j = got["report"], got["judge"]
    return {"run": name, "success": rep["success"], "collisions": sum(rep["collisions"].values()),
            "formation_error_rms_m": j["formation_error_rms_m"], "goal_error_m": j["goal_error_m"].get("0"),
            "leader_time_to_goal_s": rep["leader_time_to_goal_s"],
            "estimate_vs_site_rms_m": j["estimate_error_rms_m"].get("0"), "clearance_m": j["clearance_m"].get("0"),
            "virtual_returns": ((rep.get("mixed") or {}).get("virtual_returns") or {}).get("0")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=1, help="seeds 0..N-1 per row")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "mixed-bench")
    ap.add_argument("--followers", type=int, choices=range(1, len(FOLLOWERS) + 1), default=4,
                    help="simulated followers of the real leader")
    a = ap.parse_args()
    import subprocess
    import time

    ep = free_tcp_endpoint()
    router = subprocess.Popen([sys.executable, "-m", "stack.comm.router", "--listen", ep], cwd=ROOT,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(2.0)  # the router listens
    rows = []
    try:
        jobs = [(seed, s) for seed in range(a.seeds) for s in ["sim", *SOURCES]]
        for seed, source in tqdm(jobs, desc="mixed bench", unit="run"):
            raw, out = scenario(seed, a.followers), a.out / f"seed{seed}"
            if source == "sim":
                got, name = all_simulated(raw, out / "all-simulated", ep), "all simulated"
            else:
                name = "mixed, estimate" if source is None else f"mixed, mocap {source[0]} Hz {source[1]} ms"
                mocap = () if source is None else (f"0:{MOCAP_KEY}:{source[0]}:{source[1]}",)
                got = run_mixed(mixed(raw, source), out / name.replace(", ", "-").replace(" ", "-"), ep,
                                mocap=mocap, fleet=f"mx{seed}")
            rows.append({"seed": seed, **row(name, got)})
    finally:
        router.terminate()
        router.wait(10)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "mixed_bench.json").write_text(json.dumps(rows, indent=2))
    md = table(rows)
    (a.out / "mixed_bench.md").write_text(md)
    plot_tracks(a.out / "seed0" / "mixed-estimate", a.out / "mixed_tracks.png")
    print(md)
    print(f"written: {a.out / 'mixed_bench.md'}, {a.out / 'mixed_bench.json'}")
    return 0


def plot_tracks(run: Path, png: Path) -> None:
    """One mixed run's tracks on both worlds' truth: the real robot where the site had it (and where its pose
    source put it in the fleet's world), the simulated robots, the site's wall and the virtual cylinder."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import yaml

    raw = yaml.safe_load((run / "mixed.yaml").read_text())
    sc = parse_scenario(raw, str(run / "mixed.yaml"))
    with np.load(run / "run" / "truth.npz") as z, np.load(run / "site" / "truth.npz") as s:
        fleet, site = {k: z[k] for k in z.files}, {k: s[k] for k in s.files}
    fig, ax = plt.subplots(figsize=(9, 4.2), dpi=110)
    for o in sc.obstacles:
        if o.type == "cylinder":
            ax.add_patch(plt.Circle((o.x, o.y), o.radius, color="#9b6bff" if o.virtual else "#8c5a4d",
                                    alpha=0.5 if o.virtual else 0.9, label="virtual cylinder" if o.virtual else None))
        else:
            (x0, y0), (x1, y1) = o.start, o.end
            ax.plot([x0, x1], [y0, y1], color="#8c5a4d", lw=3, label="wall (in the site)")
    wall = fleet["wall"]
    ids = [int(i) for i in fleet["ids"]]
    for r in sc.robots:
        j = ids.index(r.id)
        if r.embodiment == "real":
            ax.plot(site["x"][:, 0], site["y"][:, 0], color="#1a9c4c", lw=2.2, label=f"robot {r.id}: real (site truth)")
            ax.plot(fleet["x"][:, j], fleet["y"][:, j], "--", color="#7fd39f", lw=1.2,
                    label=f"robot {r.id}: where its pose source put it")
        else:
            ax.plot(fleet["x"][:, j], fleet["y"][:, j], color="#2a66d9", lw=1.2, alpha=0.9,
                    label="simulated robots" if r.id == 1 else None)
    k = len(wall) // 2  # the formation half-way, on both truths
    sx = float(np.interp(wall[k], site["wall"], site["x"][:, 0]))
    sy = float(np.interp(wall[k], site["wall"], site["y"][:, 0]))
    for r in sc.robots:
        j = ids.index(r.id)
        x, y = (sx, sy) if r.embodiment == "real" else (fleet["x"][k, j], fleet["y"][k, j])
        ax.add_patch(plt.Circle((x, y), r.radius, fill=False, color="#1a9c4c" if r.embodiment == "real" else "#2a66d9"))
    ax.plot(*sc.formation.goal, "x", color="k", ms=9, label="goal")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (site frame)")
    ax.set_ylabel("y [m]")
    n = len(ids) - 1
    ax.set_title(f"a real Jackal (stand-in site) and {n} simulated robot{'s' if n != 1 else ''}, judged on both worlds' truth")
    ax.legend(loc="lower left", fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def table(rows: list[dict]) -> str:
    def f(x, nd=3):
        return "-" if x is None else f"{x:.{nd}f}"

    lines = ["| run | seed | success | collisions | formation error rms [m] (truth) | leader goal error [m] (truth) "
             "| leader time to goal [s] | pose source vs site truth rms [m] | real-sim clearance [m] | merged returns |",
             "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        v = r["virtual_returns"] or {}
        lines.append(f"| {r['run']} | {r['seed']} | {'yes' if r['success'] else 'no'} | {r['collisions']} | "
                     f"{f(r['formation_error_rms_m'])} | {f(r['goal_error_m'])} | {f(r['leader_time_to_goal_s'], 1)} | "
                     f"{f(r['estimate_vs_site_rms_m'])} | {f(r['clearance_m'], 2)} | {v.get('merged_returns', '-')} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
