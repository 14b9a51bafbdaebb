"""Mixed reality without a real robot: a stand-in for the real site, for tests and ``bench/mixed_bench.py``.

A fleet with real robots (``robots[i].embodiment: real``) needs them to be somewhere. Here that somewhere
is a second world process of ours that the fleet's world does not know (``stack-world --no-agents
--realtime`` on the scenario :func:`reality_scenario` writes): it hosts each real robot as the simulated
device behind its driver (a hardware-like Jackal: its own odom frame, rates, clock, drops) in the obstacles
that stand in the site (those not marked ``virtual``), and nothing else. The real robot's agent runs
``--driver jackal`` against it as it would against the robot; ``--mocap`` adds a motion-capture system.
"""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

SITE_FLEET = "site"
"""The stand-in site's fleet name (its keys: ``stack/site/...``; its Jackals: ``jackal/site/robot<id>``)."""


def reality_scenario(raw: dict[str, Any], fleet: str = SITE_FLEET) -> dict[str, Any]:
    """The stand-in site of the scenario ``raw`` (parsed YAML): its real robots, simulated on their own drivers'
    devices (not their agents: those join the fleet), and its obstacles that are not virtual; each robot's goal is
    where it starts (the site runs until stopped: ``--no-stop-early``)."""
    out = copy.deepcopy(raw)
    out["name"] = f"{raw.get('name', 'scenario')}-site"
    robots = [r for r in out["robots"] if r.get("embodiment") == "real"]
    if not robots:
        raise ValueError("the scenario has no real robot (robots[i].embodiment: real)")
    for r in robots:
        for key in ("embodiment", "pose_source", "role"):
            r.pop(key, None)
        r["goal"] = list(r["pose"][:2])
        lidar = r.get("lidar")
        if isinstance(lidar, dict):
            for key in ("virtual", "virtual_timeout", "virtual_lost_speed"):
                lidar.pop(key, None)
        driver = r.get("driver")
        if isinstance(r.get(driver), dict):  # the device picks its own namespace under this fleet
            r[driver] = {k: v for k, v in r[driver].items() if k != "namespace"}
    out["robots"] = robots
    defaults = out.get("robot")
    if isinstance(defaults, dict) and isinstance(defaults.get("lidar"), dict):
        for key in ("virtual", "virtual_timeout", "virtual_lost_speed"):
            defaults["lidar"].pop(key, None)
    obstacles = ((out.get("world") or {}).get("obstacles")) or []
    out["world"] = {"obstacles": [o for o in obstacles if not o.get("virtual")]}
    out.pop("formation", None)
    out["coordination"] = "arrival_time"
    return out


def site_namespace(robot_id: int, fleet: str = SITE_FLEET) -> str:
    """Where the stand-in site's Jackal ``robot_id`` is on Zenoh (its ``jackal.namespace`` in the fleet)."""
    return f"jackal/{fleet}/robot{robot_id}"


class Site:
    """The stand-in site as a process (``stack-world --no-agents --realtime`` on :func:`reality_scenario`), on the
    router at ``endpoint``; its truth (``truth.npz``, with each row's wall time) in ``out`` once it stops."""

    def __init__(self, raw: dict[str, Any], out: Path, endpoint: str, *, mocap: tuple[str, ...] = (),
                 duration: float = 600.0, fleet: str = SITE_FLEET):
        self.raw, self.out, self.endpoint, self.mocap, self.duration, self.fleet = raw, out, endpoint, mocap, duration, fleet
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> "Site":
        self.out.mkdir(parents=True, exist_ok=True)
        path = self.out / "site.yaml"
        path.write_text(yaml.safe_dump(reality_scenario(self.raw, self.fleet), sort_keys=False))
        argv = [sys.executable, "-m", "stack.sim_bridge", "--scenario", str(path), "--connect", self.endpoint,
                "--fleet", self.fleet, "--realtime", "--no-agents", "--no-stop-early", "--out", str(self.out),
                "--duration", f"{self.duration:g}"]
        for m in self.mocap:
            argv += ["--mocap", m]
        log = open(self.out / "site.log", "w")  # noqa: SIM115 - the child holds it
        self.proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        deadline = time.monotonic() + 60.0
        while not (self.out / "devices.json").exists():  # its devices are up
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the stand-in site did not come up: {(self.out / 'site.log').read_text()[-400:]}")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc) -> None:
        if self.proc is not None:
            _terminate(self.proc)

    def truth(self) -> dict[str, np.ndarray]:
        with np.load(self.out / "truth.npz") as z:
            return {k: z[k] for k in z.files}


def judge(sc, fleet_truth: dict[str, np.ndarray], site_truth: dict[str, np.ndarray]) -> dict[str, Any]:
    """A mixed run judged on both worlds' truth: each real robot where the site had it (not its estimate), each
    simulated robot where the fleet's world had it, matched by wall time. The least centre distance between a real
    and a simulated robot less their radii (< 0: they touched), the real robots' final distances to their goals
    (the formation's for a leader), and their estimate's error against the site's truth (RMS, m)."""
    real = [r for r in sc.robots if r.embodiment == "real"]
    fleet_ids, site_ids = [int(i) for i in fleet_truth["ids"]], [int(i) for i in site_truth["ids"]]
    tw = fleet_truth["wall"]
    out: dict[str, Any] = {"clearance_m": {}, "goal_error_m": {}, "estimate_error_rms_m": {}}
    for r in real:
        j = site_ids.index(r.id)
        sx = np.interp(tw, site_truth["wall"], site_truth["x"][:, j])
        sy = np.interp(tw, site_truth["wall"], site_truth["y"][:, j])
        jf = fleet_ids.index(r.id)
        out["estimate_error_rms_m"][str(r.id)] = float(np.sqrt(np.mean(
            (fleet_truth["x"][:, jf] - sx) ** 2 + (fleet_truth["y"][:, jf] - sy) ** 2)))
        gaps = [np.hypot(fleet_truth["x"][:, fleet_ids.index(o.id)] - sx, fleet_truth["y"][:, fleet_ids.index(o.id)] - sy)
                - r.radius - o.radius for o in sc.robots if o.embodiment == "simulated"]
        out["clearance_m"][str(r.id)] = float(np.min(gaps)) if gaps else None
        goal = r.goal if r.goal is not None else (sc.formation.goal if sc.formation and sc.formation.leader == r.id else None)
        if goal is not None:
            out["goal_error_m"][str(r.id)] = float(np.hypot(sx[-1] - goal[0], sy[-1] - goal[1]))
        fleet_truth = dict(fleet_truth, x=fleet_truth["x"].copy(), y=fleet_truth["y"].copy())
        fleet_truth["x"][:, jf], fleet_truth["y"][:, jf] = sx, sy  # from here on: the real robot where it was
    out["formation_error_rms_m"] = formation_error_rms(sc, fleet_truth)
    return out


def formation_error_rms(sc, truth: dict[str, np.ndarray]) -> float | None:
    """RMS over followers and steps of |position - slot| (INTERFACES.md section 3), the slots placed on the leader's
    true position (eq. (3), the final slots); None without a formation."""
    from ..models.geometry import slot_position

    f = sc.formation
    if f is None:
        return None
    ids = [int(i) for i in truth["ids"]]
    li = ids.index(f.leader)
    err = [np.hypot(*(np.array(slot_position((truth["x"][k, li], truth["y"][k, li]), slot))
                      - [truth["x"][k, ids.index(rid)], truth["y"][k, ids.index(rid)]]))
           for rid, slot in f.final_slots.items() for k in range(len(truth["t"]))]
    return float(np.sqrt(np.mean(np.square(err))))


def run_mixed(raw: dict[str, Any], out: Path, endpoint: str, *, mocap: tuple[str, ...] = (), fleet: str = "mixed",
              timeout_s: float = 180.0) -> dict[str, Any]:
    """One mixed run on the router at ``endpoint``: the stand-in site (with ``mocap``), ``stack-fleet run --realtime``
    for the simulated robots, and each real robot's own ``stack-agent`` (as on the robot). Returns the fleet's report
    and :func:`judge`'s verdict on both worlds' truth (``{"report": ..., "judge": ...}``); the logs are in ``out``."""
    from ..scenario import parse_scenario

    out.mkdir(parents=True, exist_ok=True)
    path = out / "mixed.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    sc = parse_scenario(raw, str(path))
    env = dict(os.environ, PYTHONUNBUFFERED="1")

    def start(args: list[str], log: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", *args], stdout=open(out / log, "w"),  # noqa: SIM115
                                stderr=subprocess.STDOUT, env=env)

    with Site(raw, out / "site", endpoint, mocap=mocap) as site:
        run = start(["stack.fleet", "run", str(path), "--realtime", "--connect", endpoint, "--fleet", fleet,
                     "--out", str(out / "run"), "--no-progress", "--no-plots"], "fleet.log")
        agents = [start(["stack.agents", "--id", str(r.id), "--scenario", str(path), "--connect", endpoint,
                         "--fleet", fleet], f"agent{r.id}.log") for r in sc.robots if r.embodiment == "real"]
        try:
            run.wait(timeout_s)
        finally:
            for p in [*agents, run]:  # each agent stops its robot (zero velocity) on SIGTERM
                _terminate(p)
    report = json.loads((out / "run" / "report.json").read_text())
    with np.load(out / "run" / "truth.npz") as z:
        fleet_truth = {k: z[k] for k in z.files}
    return {"report": report, "judge": judge(sc, fleet_truth, site.truth())}


def _terminate(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
