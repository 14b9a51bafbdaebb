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
    f = sc.formation

    # distances and collisions
    dmin_t, _ = pairwise_distances(X, Y)  # a dead robot's body is still there to collide with
    _, dmax_t = pairwise_distances(X, Y, alive)  # how far apart the live ones spread
    rr = 0
    if N > 1:
        for a in range(N):
            for b in range(a + 1, N):
                rr += _entries(np.hypot(X[:, a] - X[:, b], Y[:, a] - Y[:, b]) < radii[a] + radii[b])
    obs_d = distance_to_obstacles(X, Y, sc.obstacles) if sc.obstacles else np.full(X.shape, np.inf)
    ro = _entries(obs_d < radii[None, :]) if sc.obstacles else 0
    dobs_t = obs_d.min(axis=1)

    # formation: who leads and every follower's slot at each step, from the leader's true position,
    # eq. (3), with the schedule and the failover rule (FormationConfig.resolve) as the agents apply them
    robots: dict[str, dict] = {}
    leader_time = None
    connectivity = None
    lead = np.full(K, -1)
    TX, TY = np.full((K, N), np.nan), np.full((K, N), np.nan)  # each robot's target: the goal or its slot
    if f is not None:
        ok = np.ones(K, bool)
        for k in range(K):
            dead = {ids[j] for j in np.nonzero(~alive[k])[0]}
            leader, slots = f.resolve(float(t[k]), dead)
            if leader is None:
                continue
            li = idx[leader]
            lead[k] = leader
            TX[k, li], TY[k, li] = f.goal
            for rid, sl in slots.items():
                j = idx[rid]
                TX[k, j], TY[k, j] = X[k, li] + sl.L * math.cos(sl.psi), Y[k, li] + sl.L * math.sin(sl.psi)
                ok[k] &= math.hypot(X[k, j] - X[k, li], Y[k, j] - Y[k, li]) <= sc.robot(rid).comm_range
        lj = np.array([idx[int(r)] if r >= 0 else 0 for r in lead])
        d_goal = np.hypot(X[np.arange(K), lj] - f.goal[0], Y[np.arange(K), lj] - f.goal[1])
        hit = np.nonzero((lead >= 0) & (d_goal <= sc.success.goal_tolerance))[0]
        leader_time = float(t[hit[0]]) if len(hit) else None
        connectivity = float(ok.mean())
    else:
        for j, rid in enumerate(ids):
            TX[:, j], TY[:, j] = sc.robot(rid).goal
    following = np.zeros((K, N), bool)
    if f is not None:
        following = ~np.isnan(TX) & (lead[:, None] != np.array(ids)[None, :]) & ~_frozen(faults, t, ids)
    err = np.hypot(X - TX, Y - TY)[following]
    slot_xy = {rid: (np.where(following[:, j], TX[:, j], np.nan), np.where(following[:, j], TY[:, j], np.nan))
               for j, rid in enumerate(ids) if following[:, j].any()}

    arrivals = []
    for rid in ids:
        j = idx[rid]
        seg = np.hypot(np.diff(X[:, j]), np.diff(Y[:, j]))
        live = ~np.isnan(TX[:, j])  # steps at which the robot had a target (not gone)
        ex, ey = TX[:, j] - X[:, j], TY[:, j] - Y[:, j]
        # arrival: first time within goal tolerance of the final target (the goal, or the slot at the goal)
        fx, fy = TX[-1, j], TY[-1, j]
        if f is not None and following[-1, j]:
            li = idx[int(lead[-1])]
            fx, fy = TX[-1, j] - X[-1, li] + f.goal[0], TY[-1, j] - Y[-1, li] + f.goal[1]
        near = np.nonzero(np.hypot(X[:, j] - fx, Y[:, j] - fy) <= sc.success.goal_tolerance)[0] if live.any() else []
        arrival = float(t[near[0]]) if len(near) else None
        arrivals.append(arrival)
        ex, ey, tj = ex[live], ey[live], t[live]
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
            "error_convergence_time_s": {"x": _f(_converged_since(tj, ex, CONVERGED_M)) if len(tj) else None,
                                         "y": _f(_converged_since(tj, ey, CONVERGED_M)) if len(tj) else None},
            "final_error_m": _f(math.hypot(ex[-1], ey[-1])) if len(tj) else None,
            "estimator_rmse_m": _f(rmse),
            "situations": dict(d.situations) if d is not None else {},
            "fixes": {"used": d.fixes_used, "rejected": d.fixes_rejected} if d is not None else None,
            "estimator_inputs_rejected": d.inputs_rejected if d is not None else None,
            "sensor_stale_stops": d.sensor_stale if d is not None else None,
            "states_rejected": d.rejected_states if d is not None else None,
            "driver_fault": (d.fault or None) if d is not None else None,
            "neighbour_waits_timed_out": d.neighbour_waits_timed_out if d is not None else None,
            "device_odom_late": d.device_odom_late if d is not None else None,
            "scans_from_driver": d.scans_from_driver if d is not None else None,
            "shield_masked": d.shield_masked if d is not None else None,
            "led_since_s": d.led_since if d is not None else None,
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
            worst = np.where(following, np.hypot(X - TX, Y - TY), 0.0).max(axis=1)
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
        reached = all(a is not None and a <= max_time for a, rid in zip(arrivals, ids) if alive[-1, idx[rid]])
    collided = (rr + ro) > 0
    success = bool(reached and not (sc.success.no_collisions and collided) and not crashed)

    faults = _fault_details(faults, diags, f) + _device_faults(world, diags, t, z["v"], idx)

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
        "late_steps": world.get("late_steps"),  # lock-step: steps the world took without an agent's answer
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


def _device_faults(world: dict, diags: dict, t: np.ndarray, V: np.ndarray, idx: dict[int, int]) -> list:
    """Each injected device failure (``--device-fault``): what the driver said (``driver_fault``) and how
    long until the robot stood still (``stopped_s``: speed under 0.05 m/s from then on)."""
    out = []
    for e in world.get("events", []):
        if e.get("event") != "device fault":
            continue
        rid, t0 = e["robot"], e["t"]
        d = diags.get(rid)
        moving = np.nonzero((t >= t0) & (np.abs(V[:, idx[rid]]) >= 0.05))[0]
        stopped = t0 if moving.size == 0 else (float(t[moving[-1] + 1]) if moving[-1] + 1 < len(t) else None)
        out.append({"robot": rid, "kind": "device_fault", "what": e.get("what"), "sim_time_s": t0,
                    "driver_fault": (d.fault or None) if d is not None else None,
                    "stopped_s": None if stopped is None else round(stopped - t0, 3)})
    return out


def _fault_details(faults: list, diags: dict, f) -> list:
    """Each kill or freeze with how long every other agent took to drop the robot (``noticed_s``) and,
    for the leader, who took over and how long after the fault it commanded as leader."""
    out = []
    gone: set[int] = set()
    for fault in sorted(faults, key=lambda x: x.get("sim_time_s") or 0.0):
        fault = dict(fault)
        rid, t0 = fault["robot"], fault.get("sim_time_s")
        if fault["kind"] == "restarted":
            gone.discard(rid)
        if fault["kind"] in ("killed", "frozen", "crashed") and t0 is not None:
            fault["noticed_s"] = {str(a): round(d.noticed[rid] - t0, 3) for a, d in sorted(diags.items())
                                  if a != rid and rid in d.noticed and d.noticed[rid] >= t0 - 1e-9}
            was_leader = f is not None and f.resolve(t0, gone)[0] == rid
            if fault["kind"] != "frozen":
                gone.add(rid)
            if was_leader and fault["kind"] != "frozen":
                took = sorted((d.led_since, a) for a, d in diags.items()
                              if a != rid and d.led_since is not None and d.led_since >= t0 - 1e-9)
                if took:
                    fault["new_leader"] = took[0][1]
                    fault["takeover_s"] = round(took[0][0] - t0, 3)
        out.append(fault)
    return out


def _frozen(faults: list, t: np.ndarray, ids: list[int]) -> np.ndarray:
    """(K, N): the robot's agent was frozen (--freeze) and not yet restarted: out of the formation."""
    out = np.zeros((len(t), len(ids)), bool)
    for fault in sorted(faults, key=lambda x: x.get("sim_time_s") or 0.0):
        if fault.get("robot") not in ids or fault.get("sim_time_s") is None:
            continue
        j = ids.index(fault["robot"])
        if fault["kind"] == "frozen":
            out[t >= fault["sim_time_s"] - 1e-9, j] = True
        elif fault["kind"] == "restarted":
            out[t >= fault["sim_time_s"] - 1e-9, j] = False
    return out
