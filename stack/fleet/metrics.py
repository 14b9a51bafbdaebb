"""The report's metrics, one function each, over a run's ground-truth log (INTERFACES.md section 3).

Definitions follow the contract: distances centre to centre (robots) and centre to
obstacle surface, from ground truth; a collision is an entry into centre distance < 2
radius (robots) or < radius (obstacle); connectivity is the fraction of steps in which
every live follower is within comm range of the leader.
"""

from __future__ import annotations

import math

import numpy as np

from ..agents.timing import LatencyHistogram
from ..scenario import Scenario
from ..sim_bridge.geometry import distance_to_obstacles, pairwise_distances
from .truth import Targets, TruthLog

CONVERGED_M = 0.05  # error_convergence_time_s threshold per axis
NEAR_OBSTACLE_M = 1.0  # a robot this close to an obstacle surface (clearance) is passing it
RECOVERED_M = 0.1  # formation recovered: every follower within this of its slot
STOPPED_MPS = 0.05  # a robot slower than this stands still (device faults' stopped_s)
COMM_COUNTERS = ("sent", "received", "delivered", "dropped_loss", "dropped_range", "malformed")


def rounded(x) -> float | None:
    """JSON-safe float to 4 decimals: None for None, inf and nan."""
    if x is None:
        return None
    x = float(x)
    return round(x, 4) if math.isfinite(x) else None


def entries(mask: np.ndarray) -> int:
    """Number of rising edges (False -> True) along axis 0, the first row counting if True."""
    m = mask.astype(bool)
    prev = np.concatenate([np.zeros_like(m[:1]), m[:-1]], axis=0)
    return int((m & ~prev).sum())


def converged_since(t: np.ndarray, err: np.ndarray, thr: float) -> float | None:
    """Earliest time after which |err| stays below thr to the end (None if the last sample is above)."""
    bad = np.nonzero(np.abs(err) >= thr)[0]
    if len(bad) == 0:
        return float(t[0])
    if bad[-1] == len(t) - 1:
        return None
    return float(t[bad[-1] + 1])


def radii(sc: Scenario, log: TruthLog) -> np.ndarray:
    return np.array([sc.robot(r).radius for r in log.ids])


def clearance(sc: Scenario, log: TruthLog) -> np.ndarray:
    """(K, N) distance from each robot's centre to the nearest obstacle surface (inf without obstacles)."""
    if not sc.obstacles:
        return np.full(log.x.shape, np.inf)
    return distance_to_obstacles(log.x, log.y, sc.obstacles)


# --- distances and collisions ---------------------------------------------------------------------

def collisions(sc: Scenario, log: TruthLog, clear: np.ndarray) -> dict:
    """Entries into contact: robot pairs (centre distance < sum of radii; a dead robot's body still
    counts) and robots with obstacles (clearance < radius)."""
    r = radii(sc, log)
    rr = 0
    for a in range(len(log.ids)):
        for b in range(a + 1, len(log.ids)):
            rr += entries(np.hypot(log.x[:, a] - log.x[:, b], log.y[:, a] - log.y[:, b]) < r[a] + r[b])
    ro = entries(clear < r[None, :]) if sc.obstacles else 0
    return {"robot_robot": rr, "robot_obstacle": ro}


def distance_series(log: TruthLog, clear: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K,) per step: the closest robot pair (dead bodies included), the farthest live pair, the closest
    robot to an obstacle."""
    dmin, _ = pairwise_distances(log.x, log.y)
    _, dmax = pairwise_distances(log.x, log.y, log.alive)
    return dmin, dmax, clear.min(axis=1)


def distance_fields(sc: Scenario, log: TruthLog, clear: np.ndarray) -> dict:
    dmin, dmax, dobs = distance_series(log, clear)
    several = len(log.ids) > 1
    return {"min_robot_distance_m": rounded(dmin.min()) if several else None,
            "min_obstacle_distance_m": rounded(dobs.min()) if sc.obstacles else None,
            "max_robot_distance_m": rounded(dmax.max()) if several else None}


# --- the formation -------------------------------------------------------------------------------

def connectivity(sc: Scenario, tg: Targets) -> float | None:
    """Fraction of steps with every follower within comm range of the leader (None without a formation)."""
    return None if sc.formation is None else float(tg.connected.mean())


def leader_time_to_goal(sc: Scenario, log: TruthLog, tg: Targets) -> float | None:
    """First time the robot leading then was within goal tolerance of the formation's goal."""
    f = sc.formation
    if f is None:
        return None
    K = log.steps
    cols = np.array([log.column(int(r)) if r >= 0 else 0 for r in tg.leader])
    d_goal = np.hypot(log.x[np.arange(K), cols] - f.goal[0], log.y[np.arange(K), cols] - f.goal[1])
    hit = np.nonzero((tg.leader >= 0) & (d_goal <= sc.success.goal_tolerance))[0]
    return float(log.t[hit[0]]) if len(hit) else None


def formation_error_rms(log: TruthLog, tg: Targets) -> float | None:
    """RMS over followers and steps of |position - slot|."""
    err = tg.error(log)[tg.following]
    return float(np.sqrt(np.mean(err ** 2))) if err.size else None


def obstacle_recovery(sc: Scenario, log: TruthLog, tg: Targets, clear: np.ndarray) -> tuple[float | None, float | None]:
    """(cleared_at, recovery): the last step at which a robot had under NEAR_OBSTACLE_M of clearance,
    and from then how long until every follower stays within RECOVERED_M of its slot."""
    if sc.formation is None or not sc.obstacles or not tg.following.any():
        return None, None
    near = (clear - radii(sc, log)[None, :] < NEAR_OBSTACLE_M).any(axis=1)
    if not near.any():
        return None, None
    k0 = int(np.nonzero(near)[0][-1])
    cleared_at = float(log.t[k0])
    worst = np.where(tg.following, tg.error(log), 0.0).max(axis=1)
    since = converged_since(log.t[k0:], worst[k0:], RECOVERED_M)
    return cleared_at, None if since is None else since - cleared_at


def arrival_spread_steps(sc: Scenario, arrivals: list[float | None]) -> int | None:
    """Arrival-time tasks (no formation): (last arrival - first arrival) / dt, Chang 2020 Tables 2-3."""
    if sc.formation is not None or any(a is None for a in arrivals):
        return None
    return round((max(arrivals) - min(arrivals)) / sc.dt)


# --- one robot -----------------------------------------------------------------------------------

def path_length(log: TruthLog, j: int) -> float:
    return float(np.hypot(np.diff(log.x[:, j]), np.diff(log.y[:, j])).sum())


def arrival_time(sc: Scenario, log: TruthLog, tg: Targets, j: int) -> float | None:
    """First time within goal tolerance of the robot's final target: its goal, or (a follower at the
    end) its final slot placed around the formation's goal."""
    if np.isnan(tg.tx[:, j]).all():
        return None
    fx, fy = tg.tx[-1, j], tg.ty[-1, j]
    f = sc.formation
    if f is not None and tg.following[-1, j]:
        li = log.column(int(tg.leader[-1]))
        fx, fy = fx - log.x[-1, li] + f.goal[0], fy - log.y[-1, li] + f.goal[1]
    near = np.nonzero(np.hypot(log.x[:, j] - fx, log.y[:, j] - fy) <= sc.success.goal_tolerance)[0]
    return float(log.t[near[0]]) if len(near) else None


def _target_errors(log: TruthLog, tg: Targets, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, ex, ey) at the steps at which robot column j had a target: target - position per axis."""
    has = ~np.isnan(tg.tx[:, j])
    return log.t[has], (tg.tx[:, j] - log.x[:, j])[has], (tg.ty[:, j] - log.y[:, j])[has]


def error_convergence(log: TruthLog, tg: Targets, j: int) -> dict:
    """Per axis, the earliest time after which |target - position| stays below CONVERGED_M (None if never)."""
    t, ex, ey = _target_errors(log, tg, j)
    if not len(t):
        return {"x": None, "y": None}
    return {"x": rounded(converged_since(t, ex, CONVERGED_M)), "y": rounded(converged_since(t, ey, CONVERGED_M))}


def final_error(log: TruthLog, tg: Targets, j: int) -> float | None:
    """|target - position| at the last step the robot had a target."""
    t, ex, ey = _target_errors(log, tg, j)
    return math.hypot(ex[-1], ey[-1]) if len(t) else None


def estimator_rmse(log: TruthLog, j: int, estimates: list[tuple[int, float, float]]) -> float | None:
    """RMS distance between the (step, x, y) estimates an agent published and ground truth at those steps."""
    if not estimates:
        return None
    steps = np.array([e[0] for e in estimates])
    valid = (steps >= 0) & (steps < log.steps)
    if not valid.any():
        return None
    ex = np.array([e[1] for e in estimates])[valid] - log.x[steps[valid], j]
    ey = np.array([e[2] for e in estimates])[valid] - log.y[steps[valid], j]
    return float(np.sqrt(np.mean(ex ** 2 + ey ** 2)))


DIAG_FIELDS = ("fixes", "estimator_inputs_rejected", "sensor_stale_stops", "states_rejected", "driver_fault",
               "neighbour_waits_timed_out", "device_odom_late", "scans_from_driver", "shield_masked", "guard_caps",
               "guard_slides", "guard_brakes", "led_since_s", "stuck", "device_odom_strays", "odom_stale_stops", "lidar_stale_stops")


def diag_fields(d) -> dict:
    """What the agent's last diag said (``situations`` empty and the rest None without one)."""
    if d is None:
        return {"situations": {}, **dict.fromkeys(DIAG_FIELDS)}
    return {"situations": dict(d.situations), "fixes": {"used": d.fixes_used, "rejected": d.fixes_rejected},
            "estimator_inputs_rejected": d.inputs_rejected, "sensor_stale_stops": d.sensor_stale,
            "states_rejected": d.rejected_states, "driver_fault": d.fault or None,
            "neighbour_waits_timed_out": d.neighbour_waits_timed_out, "device_odom_late": d.device_odom_late,
            "scans_from_driver": d.scans_from_driver, "shield_masked": d.shield_masked, "guard_caps": d.guard_caps,
            "guard_slides": d.guard_slides, "guard_brakes": d.guard_brakes, "led_since_s": d.led_since,
            "stuck": d.stuck, "device_odom_strays": d.device_odom_strays, "odom_stale_stops": d.odom_stale,
            "lidar_stale_stops": d.lidar_stale}


def robot_entry(sc: Scenario, log: TruthLog, tg: Targets, rid: int, diag, estimates: list) -> dict:
    """``robots.<id>`` of the report."""
    j = log.column(rid)
    r = sc.robot(rid)
    return {"role": r.role or "peer", "policy": r.policy, "driver": r.driver,
            "path_length_m": rounded(path_length(log, j)),
            "arrival_time_s": rounded(arrival_time(sc, log, tg, j)),
            "error_convergence_time_s": error_convergence(log, tg, j),
            "final_error_m": rounded(final_error(log, tg, j)),
            "estimator_rmse_m": rounded(estimator_rmse(log, j, estimates)),
            **diag_fields(diag),
            "alive_at_end": bool(log.alive[-1, j])}


# --- the agents' counters ------------------------------------------------------------------------

def comm_totals(diags: dict, world: dict) -> dict:
    """Message counters summed over agents, per link as the contract counts them (sent = delivered +
    dropped_loss + dropped_range, plus any in flight: every state reaches every receiver's radio model,
    so links sent = messages offered there); ``broadcasts``: the states the agents published."""
    comm = {k: sum(getattr(d, k) for d in diags.values()) for k in COMM_COUNTERS}
    comm["malformed"] += int(world.get("malformed", 0))
    comm["broadcasts"] = comm["sent"]
    comm["sent"] = comm["received"]
    return comm


def latency_percentiles(diags: dict, hist: str) -> dict:
    """p50, p99 [ms] and sample count of one latency histogram (``loop_hist``, ``compute_hist``,
    ``state_latency_hist``) merged over agents."""
    h = LatencyHistogram()
    for d in diags.values():
        h.merge(getattr(d, hist))
    return {"p50": rounded(h.percentile(50)), "p99": rounded(h.percentile(99)), "samples": h.total}


def success(sc: Scenario, log: TruthLog, leader_time: float | None, arrivals: list[float | None],
            hits: dict, crashed: list) -> bool:
    """The leader (or every live peer) at its goal within max_time, no collisions if asked, nothing crashed."""
    max_time = sc.success.max_time or sc.duration
    if sc.formation is not None:
        reached = leader_time is not None and leader_time <= max_time
    else:
        reached = all(a is not None and a <= max_time for a, alive in zip(arrivals, log.alive[-1]) if alive)
    collided = sum(hits.values()) > 0
    return bool(reached and not (sc.success.no_collisions and collided) and not crashed)


# --- livelock ------------------------------------------------------------------------------------

RESOLVED_BY = ("escape", "detour", "target", "gave_up", "plan")


def livelock(diags: dict) -> dict | None:
    """The agents' stuck detectors and leader holds summed up (``Diag.stuck``, see stack.agents.livelock):
    stuck episodes, what resolved them, those still open at the end, the leader's hold give-ups with when
    and why; None when no agent reported them (a policy or agent without the detector)."""
    got = {rid: d.stuck for rid, d in diags.items() if getattr(d, "stuck", None)}
    if not got:
        return None
    out = {"stuck_episodes": sum(int(s.get("episodes", 0)) for s in got.values()),
           "resolved_by": {k: sum(int(s.get(k, 0)) for s in got.values()) for k in RESOLVED_BY},
           "open_at_end": sum(int(s.get("open", 0)) for s in got.values()),
           "hold_give_ups": sum(int(s.get("hold_give_ups", 0)) for s in got.values())}
    out["hold_events"] = [{"leader": rid, **e} for rid, s in sorted(got.items()) for e in s.get("events", ())
                          if str(e.get("event", "")).startswith("hold-gave-up")]
    out["stuck_robots"] = sorted(rid for rid, s in got.items() if int(s.get("episodes", 0)) > 0)
    return out


def planning(diags: dict) -> dict | None:
    """Plans beside the control step (``Diag.planner``, ``stack.planning.runner``), per robot that asked for one:
    asked and adopted, compute time [ms] p50 / p99 / max, the most step time between asking and driving the plan
    [s] and the plan's age at the end [s]; None when no robot planned."""
    got = {str(rid): d.planner for rid, d in sorted(diags.items()) if getattr(d, "planner", None)}
    return got or None


# --- faults --------------------------------------------------------------------------------------

def frozen_mask(faults: list, t: np.ndarray, ids: list[int]) -> np.ndarray:
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


def fault_details(faults: list, diags: dict, formation) -> list:
    """Each kill, freeze or crash with how long every other agent took to drop the robot (``noticed_s``)
    and, for the leader, who took over and how long after the fault it commanded as leader."""
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
            was_leader = formation is not None and formation.resolve(t0, gone)[0] == rid
            if fault["kind"] != "frozen":
                gone.add(rid)
                if was_leader:
                    fault.update(_takeover(diags, rid, t0))
        out.append(fault)
    return out


def _takeover(diags: dict, rid: int, t0: float) -> dict:
    """The first agent other than ``rid`` to lead at or after ``t0``, and how long after ``t0``."""
    took = sorted((d.led_since, a) for a, d in diags.items() if a != rid and d.led_since is not None
                  and d.led_since >= t0 - 1e-9)
    return {"new_leader": took[0][1], "takeover_s": round(took[0][0] - t0, 3)} if took else {}


def device_faults(world: dict, diags: dict, log: TruthLog) -> list:
    """Each injected device failure (``--device-fault``): what the driver said (``driver_fault``) and how
    long until the robot stood still (``stopped_s``: speed under STOPPED_MPS from then on)."""
    out = []
    for e in world.get("events", []):
        if e.get("event") != "device fault":
            continue
        rid, t0 = e["robot"], e["t"]
        d = diags.get(rid)
        t = log.t
        moving = np.nonzero((t >= t0) & (np.abs(log.v[:, log.column(rid)]) >= STOPPED_MPS))[0]
        stopped = t0 if moving.size == 0 else (float(t[moving[-1] + 1]) if moving[-1] + 1 < len(t) else None)
        out.append({"robot": rid, "kind": "device_fault", "what": e.get("what"), "sim_time_s": t0,
                    "driver_fault": (d.fault or None) if d is not None else None,
                    "stopped_s": None if stopped is None else round(stopped - t0, 3)})
    return out


def two_leaders_s(diags: dict, dt: float) -> float:
    """Run time during which two or more robots led at once (each agent's ``led`` intervals, a step long each)."""
    edges = sorted((t, d) for diag in diags.values() for a, b in getattr(diag, "led", ()) for t, d in
                   ((a, 1), (b + dt, -1)))
    total, depth, since = 0.0, 0, 0.0
    for t, d in edges:
        if depth >= 2:
            total += t - since
        depth += d
        since = t
    return total


def network(world: dict, diags: dict, dt: float) -> dict:
    """Outages (the world's own, robots out of contact: start, end, robots), each agent's own router outages and
    held steps, who led when, and how long two led at once (``stack.agents.quorum``)."""
    return {
        "outages": world.get("outages", []),
        "agent_outages": {str(r): [[rounded(a), rounded(b)] for a, b in d.link_outages]
                          for r, d in sorted(diags.items()) if getattr(d, "link_outages", None)},
        "held_steps": {str(r): d.held_steps for r, d in sorted(diags.items()) if getattr(d, "held_steps", 0)},
        "tokens_kept": sum(getattr(d, "tokens_kept", 0) for d in diags.values()),
        "led": {str(r): [[rounded(a), rounded(b)] for a, b in d.led] for r, d in sorted(diags.items())
                if getattr(d, "led", None)},
        "two_leaders_s": rounded(two_leaders_s(diags, dt)),
    }
