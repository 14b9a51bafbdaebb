"""``report.json`` (INTERFACES.md section 3) from the world's ground-truth log and the agents' diag.

:func:`report_of` composes the metrics of :mod:`.metrics` over a :class:`~.truth.TruthLog`;
:func:`build_report` reads the run's folder, writes ``report.json`` and the plots.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..scenario import Scenario
from . import metrics as m
from .truth import Targets, TruthLog, targets


def build_report(sc: Scenario, out: Path, *, diags: dict, estimates: dict, faults: list, crashed: list,
                 wall_time_s: float, realtime: bool, plots: bool = True, router_restarts: list | None = None) -> dict:
    """The report of the run in ``out`` (its ``truth.npz`` and ``world.json``), written to ``out/report.json``."""
    world_path = out / "world.json"
    world = json.loads(world_path.read_text()) if world_path.exists() else {}
    if not (out / "truth.npz").exists():
        report = _empty_report(sc, wall_time_s, faults, crashed)
        (out / "report.json").write_text(json.dumps(report, indent=2))
        return report
    log = TruthLog.load(out / "truth.npz")
    tg = targets(sc, log, m.frozen_mask(faults, log.t, log.ids))
    report = report_of(sc, log, tg, world, diags=diags, estimates=estimates, faults=faults, crashed=crashed,
                       wall_time_s=wall_time_s, realtime=realtime)
    report["network"]["router_restarts"] = list(router_restarts or [])  # the fleet's own router, started again
    (out / "report.json").write_text(json.dumps(report, indent=2))
    if plots:
        _plot(sc, log, tg, out)
    return report


def report_of(sc: Scenario, log: TruthLog, tg: Targets, world: dict, *, diags: dict, estimates: dict, faults: list,
              crashed: list, wall_time_s: float, realtime: bool) -> dict:
    """The report's fields, in the contract's order and then ours (README: "Report fields beyond the contract")."""
    f = sc.formation
    clear = m.clearance(sc, log)
    hits = m.collisions(sc, log, clear)
    arrivals = [m.arrival_time(sc, log, tg, j) for j in range(len(log.ids))]
    leader_time = m.leader_time_to_goal(sc, log, tg)
    cleared_at, recovery = m.obstacle_recovery(sc, log, tg, clear)
    return {
        "scenario": sc.name,
        "seed": sc.seed,
        "dt": sc.dt,
        "policies": {str(r.id): r.policy for r in sc.robots},
        "drivers": {str(r.id): r.driver for r in sc.robots},
        "mode": "realtime" if realtime else "lockstep",
        "success": m.success(sc, log, leader_time, arrivals, hits, crashed),
        "sim_time_s": m.rounded(log.t[-1]),
        "wall_time_s": m.rounded(wall_time_s),
        "leader_time_to_goal_s": m.rounded(leader_time),
        "collisions": hits,
        **m.distance_fields(sc, log, clear),
        "connectivity": m.rounded(m.connectivity(sc, tg)),
        "formation_error_rms_m": m.rounded(m.formation_error_rms(log, tg)),
        "arrival_spread_steps": m.arrival_spread_steps(sc, arrivals),
        "formation_switches_s": [ch.at for ch in f.schedule] if f is not None else [],
        "obstacles_cleared_at_s": m.rounded(cleared_at),
        "formation_recovery_s": m.rounded(recovery),
        "robots": {str(rid): m.robot_entry(sc, log, tg, rid, diags.get(rid), estimates.get(rid, [])) for rid in log.ids},
        "comm": m.comm_totals(diags, world),
        "control_loop_ms": m.latency_percentiles(diags, "loop_hist"),
        "control_compute_ms": m.latency_percentiles(diags, "compute_hist"),
        "state_latency_ms": m.latency_percentiles(diags, "state_latency_hist"),
        "faults": m.fault_details(faults, diags, f) + m.device_faults(world, diags, log),
        "crashed": crashed,
        "end_reason": world.get("end_reason"),
        "steps": int(log.steps),
        "steps_per_s": m.rounded(world.get("steps_per_s")),
        "late_steps": world.get("late_steps"),  # lock-step: steps the world took without an agent's answer
        "planning": m.planning(diags),  # plans beside the control step: compute times, how old the plan driven was
        "livelock": m.livelock(diags),  # stuck episodes, what resolved them, the leader hold's give-ups
        "network": m.network(world, diags, sc.dt),  # outages, who led when, two_leaders_s
        "mixed": _mixed(sc, world, diags),  # real robots: where their truth came from, stale spans, virtual returns
    }


def _mixed(sc: Scenario, world: dict, diags: dict) -> dict | None:
    """Mixed reality (robots with ``embodiment: real``): which robots were real, whose truth here was their pose
    source's (their estimate or a motion-capture system, not the world's), when it was stale, and each real robot's
    virtual returns (``stack.agents.virtual``). None in an all-simulated fleet."""
    real = [r.id for r in sc.robots if r.embodiment == "real"]
    if not real:
        return None
    sources = world.get("pose_sources", {})
    return {"real_robots": real,
            "truth_from_estimate": [rid for rid in real if sources.get(str(rid), "estimate") == "estimate"],
            "truth_from_pose_source": {str(rid): sources[str(rid)] for rid in real
                                       if sources.get(str(rid), "estimate") != "estimate"},
            "poses_received": world.get("poses_received", {}), "pose_stale": world.get("pose_stale", []),
            "pose_malformed": world.get("pose_malformed", {}),
            "pose_out_of_order": world.get("pose_out_of_order", {}),
            "virtual_scans_sent": world.get("virtual_scans_sent", {}),
            "virtual_returns": {str(rid): getattr(diags.get(rid), "virtual", None) for rid in real}}


def _plot(sc: Scenario, log: TruthLog, tg: Targets, out: Path) -> None:
    from .plots import plot_distances, plot_errors, plot_trajectories

    plot_trajectories(sc, log, out / "trajectories.png")
    plot_distances(sc, log.t, *m.distance_series(log, m.clearance(sc, log)), out / "distances.png")
    errors = {rid: (np.where(tg.following[:, j], tg.tx[:, j], np.nan) - log.x[:, j],
                    np.where(tg.following[:, j], tg.ty[:, j], np.nan) - log.y[:, j])
              for j, rid in enumerate(log.ids) if tg.following[:, j].any()}
    if errors:
        plot_errors(sc, log.t, errors, out / "errors.png")


def _empty_report(sc: Scenario, wall: float, faults: list, crashed: list) -> dict:
    """The report of a run whose world wrote no log (it never started or died early)."""
    return {"scenario": sc.name, "seed": sc.seed, "dt": sc.dt, "policies": {str(r.id): r.policy for r in sc.robots},
            "success": False, "sim_time_s": None, "wall_time_s": m.rounded(wall), "leader_time_to_goal_s": None,
            "collisions": {"robot_robot": None, "robot_obstacle": None}, "min_robot_distance_m": None,
            "min_obstacle_distance_m": None, "max_robot_distance_m": None, "connectivity": None,
            "formation_error_rms_m": None, "arrival_spread_steps": None, "robots": {},
            "comm": {"sent": 0, "delivered": 0, "dropped_loss": 0, "dropped_range": 0},
            "control_loop_ms": {"p50": None, "p99": None}, "control_compute_ms": {"p50": None, "p99": None}, "faults": faults, "crashed": crashed,
            "end_reason": "no world log"}
