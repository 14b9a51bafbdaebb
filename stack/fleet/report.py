"""``report.json`` (INTERFACES.md section 3) from the world's ground-truth log and the agents' diag.

Definitions follow the contract: distances centre to centre (robots) and centre to
obstacle surface, from ground truth; a collision is an entry into centre distance < 2
radius (robots) or < radius (obstacle); connectivity is the fraction of steps in which
every live follower is within comm range of the leader.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..agents.timing import LatencyHistogram
from ..scenario import Scenario
from ..sim_bridge.geometry import distance_to_obstacles, pairwise_distances

CONVERGED_M = 0.05  # error_convergence_time_s threshold per axis
NEAR_OBSTACLE_M = 1.0  # a robot this close to an obstacle surface (clearance) is passing it
RECOVERED_M = 0.1  # formation recovered: every follower within this of its slot


def _f(x) -> float | None:
    """JSON-safe float: None for inf/nan."""
    if x is None:
        return None
    x = float(x)
    return round(x, 4) if math.isfinite(x) else None


def _entries(mask: np.ndarray) -> int:
    """Number of rising edges (False -> True) along axis 0, the first row counting if True."""
    m = mask.astype(bool)
    prev = np.concatenate([np.zeros_like(m[:1]), m[:-1]], axis=0)
    return int((m & ~prev).sum())


def _converged_since(t: np.ndarray, err: np.ndarray, thr: float) -> float | None:
    """Earliest time after which |err| stays below thr to the end (None if the last sample is above)."""
    bad = np.nonzero(np.abs(err) >= thr)[0]
    if len(bad) == 0:
        return float(t[0])
    if bad[-1] == len(t) - 1:
        return None
    return float(t[bad[-1] + 1])


def build_report(sc: Scenario, out: Path, *, diags: dict, estimates: dict, faults: list, crashed: list,
                 wall_time_s: float, realtime: bool, plots: bool = True) -> dict:
    truth_path = out / "truth.npz"
    world_path = out / "world.json"
    world = json.loads(world_path.read_text()) if world_path.exists() else {}
    if not truth_path.exists():
        report = _empty_report(sc, wall_time_s, faults, crashed)
        (out / "report.json").write_text(json.dumps(report, indent=2))
        return report
    z = np.load(truth_path)
    ids = [int(i) for i in z["ids"]]
    idx = {rid: i for i, rid in enumerate(ids)}
    t, X, Y = z["t"], z["x"], z["y"]
    alive = z["alive"]
    K, N = X.shape
    radii = np.array([sc.robot(r).radius for r in ids])
    killed = {f["robot"] for f in faults}
    f = sc.formation

    # distances and collisions
    dmin_t, dmax_t = pairwise_distances(X, Y)
    rr = 0
    if N > 1:
        for a in range(N):
            for b in range(a + 1, N):
                rr += _entries(np.hypot(X[:, a] - X[:, b], Y[:, a] - Y[:, b]) < radii[a] + radii[b])
    obs_d = distance_to_obstacles(X, Y, sc.obstacles) if sc.obstacles else np.full(X.shape, np.inf)
    ro = _entries(obs_d < radii[None, :]) if sc.obstacles else 0
    dobs_t = obs_d.min(axis=1)

    # formation: slots from the leader's true position, eq. (3)
    robots: dict[str, dict] = {}
    err_all = []
    slot_xy: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    leader_time = None
    connectivity = None
    if f is not None:
        li = idx[f.leader]
        dl = np.hypot(X[:, li] - f.goal[0], Y[:, li] - f.goal[1])
        hit = np.nonzero(dl <= sc.success.goal_tolerance)[0]
        leader_time = float(t[hit[0]]) if len(hit) else None
        ok = np.ones(K, bool)
        for rid in f.slots:
            j = idx[rid]
            sx, sy = _slot_track(f, rid, t, X[:, li], Y[:, li])
            slot_xy[rid] = (sx, sy)
            live = alive[:, j] if rid in killed else np.ones(K, bool)
            err_all.append(np.hypot(X[live, j] - sx[live], Y[live, j] - sy[live]))
            within = np.hypot(X[:, j] - X[:, li], Y[:, j] - Y[:, li]) <= sc.robot(rid).comm_range
            ok &= within | ~live
        connectivity = float(ok.mean())
    err = np.concatenate(err_all) if err_all else np.zeros(0)

    arrivals = []
    for rid in ids:
        j = idx[rid]
        seg = np.hypot(np.diff(X[:, j]), np.diff(Y[:, j]))
        if f is not None and rid == f.leader:
            gx, gy = np.full(K, f.goal[0]), np.full(K, f.goal[1])
        elif f is not None:
            gx, gy = slot_xy[rid]
        else:
            gx, gy = np.full(K, sc.robot(rid).goal[0]), np.full(K, sc.robot(rid).goal[1])
        ex, ey = gx - X[:, j], gy - Y[:, j]
        # arrival: first time within goal tolerance of the final target (the goal, or the slot at the goal)
        fx, fy = (gx[-1], gy[-1])
        if f is not None and rid != f.leader:
            last = f.final_slots[rid]
            fx, fy = f.goal[0] + last.L * math.cos(last.psi), f.goal[1] + last.L * math.sin(last.psi)
        near = np.nonzero(np.hypot(X[:, j] - fx, Y[:, j] - fy) <= sc.success.goal_tolerance)[0]
        arrival = float(t[near[0]]) if len(near) else None
        arrivals.append(arrival)
        est = estimates.get(rid, [])
        rmse = None
        if est:
            steps = np.array([e[0] for e in est])
            valid = (steps >= 0) & (steps < K)
            if valid.any():
                ex_ = np.array([e[1] for e in est])[valid] - X[steps[valid], j]
                ey_ = np.array([e[2] for e in est])[valid] - Y[steps[valid], j]
                rmse = float(np.sqrt(np.mean(ex_ ** 2 + ey_ ** 2)))
        d = diags.get(rid)
        robots[str(rid)] = {
            "role": sc.robot(rid).role or "peer",
            "policy": sc.robot(rid).policy,
            "driver": sc.robot(rid).driver,
            "path_length_m": _f(seg.sum()),
            "arrival_time_s": _f(arrival),
            "error_convergence_time_s": {"x": _f(_converged_since(t, ex, CONVERGED_M)), "y": _f(_converged_since(t, ey, CONVERGED_M))},
            "final_error_m": _f(math.hypot(ex[-1], ey[-1])),
            "estimator_rmse_m": _f(rmse),
            "situations": dict(d.situations) if d is not None else {},
            "fixes": {"used": d.fixes_used, "rejected": d.fixes_rejected} if d is not None else None,
            "estimator_inputs_rejected": d.inputs_rejected if d is not None else None,
            "sensor_stale_stops": d.sensor_stale if d is not None else None,
            "alive_at_end": bool(alive[-1, j]),
        }

    # recovery after obstacles: from the last step with a robot within NEAR_OBSTACLE_M of an obstacle's
    # surface (clearance) until every live follower stays within RECOVERED_M of its slot
    cleared_at = recovery = None
    if f is not None and sc.obstacles and slot_xy:
        near = (obs_d - radii[None, :] < NEAR_OBSTACLE_M).any(axis=1)
        if near.any():
            k0 = int(np.nonzero(near)[0][-1])
            cleared_at = float(t[k0])
            worst = np.zeros(K)
            for rid, (sx, sy) in slot_xy.items():
                j = idx[rid]
                live = alive[:, j] if rid in killed else np.ones(K, bool)
                worst = np.maximum(worst, np.where(live, np.hypot(X[:, j] - sx, Y[:, j] - sy), 0.0))
            since = _converged_since(t[k0:], worst[k0:], RECOVERED_M)
            recovery = None if since is None else since - cleared_at

    arrival_spread = None
    if f is None and all(a is not None for a in arrivals):
        arrival_spread = round((max(arrivals) - min(arrivals)) / sc.dt)

    # comm and loop timing, summed over agents
    comm = {"sent": 0, "received": 0, "delivered": 0, "dropped_loss": 0, "dropped_range": 0, "malformed": 0}
    hist = LatencyHistogram()
    lat = LatencyHistogram()
    for d in diags.values():
        for k in comm:
            comm[k] += getattr(d, k)
        hist.merge(d.loop_hist)
        lat.merge(d.state_latency_hist)
    comm["malformed"] += int(world.get("malformed", 0))
    # the contract counts per link (sent = delivered + dropped_loss + dropped_range, plus any still in flight):
    # every state reaches every receiver's radio model, so links sent = messages offered there
    comm["broadcasts"] = comm["sent"]
    comm["sent"] = comm["received"]

    # success: the leader (or every peer) at its goal within max_time, no collisions if asked
    max_time = sc.success.max_time or sc.duration
    if f is not None:
        reached = leader_time is not None and leader_time <= max_time
    else:
        reached = all(a is not None and a <= max_time for a, rid in zip(arrivals, ids) if rid not in killed)
    collided = (rr + ro) > 0
    success = bool(reached and not (sc.success.no_collisions and collided) and not crashed)

    report = {
        "scenario": sc.name,
        "seed": sc.seed,
        "dt": sc.dt,
        "policies": {str(r.id): r.policy for r in sc.robots},
        "drivers": {str(r.id): r.driver for r in sc.robots},
        "mode": "realtime" if realtime else "lockstep",
        "success": success,
        "sim_time_s": _f(t[-1]),
        "wall_time_s": _f(wall_time_s),
        "leader_time_to_goal_s": _f(leader_time),
        "collisions": {"robot_robot": rr, "robot_obstacle": ro},
        "min_robot_distance_m": _f(dmin_t.min()) if N > 1 else None,
        "min_obstacle_distance_m": _f(dobs_t.min()) if sc.obstacles else None,
        "max_robot_distance_m": _f(dmax_t.max()) if N > 1 else None,
        "connectivity": _f(connectivity),
        "formation_error_rms_m": _f(np.sqrt(np.mean(err ** 2))) if err.size else None,
        "arrival_spread_steps": arrival_spread,
        "formation_switches_s": [ch.at for ch in f.schedule] if f is not None else [],
        "obstacles_cleared_at_s": _f(cleared_at),
        "formation_recovery_s": _f(recovery),
        "robots": robots,
        "comm": comm,
        "control_loop_ms": {"p50": _f(hist.percentile(50)), "p99": _f(hist.percentile(99)), "samples": hist.total},
        "state_latency_ms": {"p50": _f(lat.percentile(50)), "p99": _f(lat.percentile(99)), "samples": lat.total},
        "faults": faults,
        "crashed": crashed,
        "end_reason": world.get("end_reason"),
        "steps": int(K),
        "steps_per_s": _f(world.get("steps_per_s")),
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))
    if plots:
        from .plots import plot_distances, plot_errors, plot_trajectories

        plot_trajectories(sc, z, out / "trajectories.png")
        plot_distances(sc, t, dmin_t, dmax_t, dobs_t, out / "distances.png")
        if slot_xy:
            plot_errors(sc, t, {rid: (sx - X[:, idx[rid]], sy - Y[:, idx[rid]]) for rid, (sx, sy) in slot_xy.items()},
                        out / "errors.png")
    return report


def _empty_report(sc: Scenario, wall: float, faults: list, crashed: list) -> dict:
    return {"scenario": sc.name, "seed": sc.seed, "dt": sc.dt, "policies": {str(r.id): r.policy for r in sc.robots},
            "success": False, "sim_time_s": None, "wall_time_s": _f(wall), "leader_time_to_goal_s": None,
            "collisions": {"robot_robot": None, "robot_obstacle": None}, "min_robot_distance_m": None,
            "min_obstacle_distance_m": None, "max_robot_distance_m": None, "connectivity": None,
            "formation_error_rms_m": None, "arrival_spread_steps": None, "robots": {},
            "comm": {"sent": 0, "delivered": 0, "dropped_loss": 0, "dropped_range": 0},
            "control_loop_ms": {"p50": None, "p99": None}, "faults": faults, "crashed": crashed,
            "end_reason": "no world log"}


def _slot_track(f, rid: int, t: np.ndarray, lx: np.ndarray, ly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Follower ``rid``'s slot over time, eq. (3), with the formation schedule's switches."""
    L = np.empty(len(t))
    psi = np.empty(len(t))
    times = [0.0] + [ch.at for ch in f.schedule]
    for i, t0 in enumerate(times):
        slot = f.slots_at(t0)[rid]
        sel = t >= t0 - 1e-9
        L[sel], psi[sel] = slot.L, slot.psi
    return lx + L * np.cos(psi), ly + L * np.sin(psi)
