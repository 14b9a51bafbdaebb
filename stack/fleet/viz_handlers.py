"""What the recorder's writer thread does with each kind of sample (:mod:`.record`): one handler per
Zenoh topic, ``handler(recorder, channels, view, key, msg, recv_ns)``; ``view`` is what it remembers of
the fleet between samples (true positions, estimates, roles, faults, the comm graph's counts)."""

from __future__ import annotations

from foxglove.messages import LogLevel

from ..agents.steplog import WHAT as STEP_IO
from ..comm import Keys
from ..comm.messages import Clock, CmdVel, Diag, FaultAck, FaultRequest, Scan, State, Truth, WorldStatus
from . import viz_messages as vm

T = vm.TOPICS
LINK_KEYS = ("delivered", "dropped_range", "dropped_loss")


def on_clock(rec, ch, v, key: str, m: Clock, recv_ns: int) -> None:
    ns = rec.stamp(m.t, recv_ns)
    v.t, v.step = m.t, m.step
    rec.write(ch.clock, T["clock"], {"step": m.step, "t": m.t, "dt": m.dt, "lockstep": m.lockstep,
                                     "answered": list(m.answered), "dead": list(m.dead)}, ns)
    rec.broadcast_time(ns)
    dead = set(m.dead)
    for rid in sorted(dead - v.dead):
        rec.event(ns, f"robot {rid}: gone (the world no longer waits for it)", LogLevel.Warning)
    for rid in sorted(v.dead - dead):
        rec.event(ns, f"robot {rid}: back", LogLevel.Info)
    v.dead = dead
    if v.scene_at is None or m.t - v.scene_at >= rec.cfg.scene_every_s - 1e-9:
        rec.write(ch.obstacles, T["obstacles"], vm.obstacles_scene(rec.sc, ns), ns)
        rec.write(ch.robots, T["robots"], vm.robots_scene(rec.sc, v.estimates, ns, v.stale), ns)
        v.scene_at = m.t
    if m.step % rec.cfg.links_window_steps == 0:
        rec.write(ch.links, T["links"], vm.links_scene(v.links_window, v.where, ns), ns)


def on_truth(rec, ch, v, key: str, m: Truth, recv_ns: int) -> None:
    ns = rec.stamp(m.t, recv_ns)
    rec.write(ch.tf, T["tf"], vm.truth_transforms(m, ns), ns)
    for rid, x, y, yaw in zip(m.ids, m.x, m.y, m.yaw):
        if rid in ch.robot:
            rec.write(ch.robot[rid]["pose"], vm.robot_topic(rid, "pose"), vm.pose_in_world(x, y, yaw, ns), ns)
    v.where = {rid: (x, y) for rid, x, y in zip(m.ids, m.x, m.y)}
    if set(m.stale) != v.stale:  # a real robot's pose went stale (or came back): drawn so at once
        for rid in sorted(set(m.stale) ^ v.stale):
            rec.event(ns, f"robot {rid}: pose " + ("stale (drawn grey, grown in the world)" if rid in m.stale else "back"),
                      LogLevel.Warning if rid in m.stale else LogLevel.Info)
        v.stale = set(m.stale)
        rec.write(ch.robots, T["robots"], vm.robots_scene(rec.sc, v.estimates, ns, v.stale), ns)
    leader, targets = vm.slot_targets(rec.sc, m, v.dead)
    rec.write(ch.slots, T["slots"], vm.slots_scene(rec.sc, targets, ns), ns)
    rec.write(ch.metrics, T["metrics"], vm.metrics(rec.sc, m, leader, targets), ns)


def on_scan(rec, ch, v, key: str, m: Scan, recv_ns: int) -> None:
    ns = rec.stamp(m.stamp, recv_ns)
    rec.write(ch.robot[m.id]["scan"], vm.robot_topic(m.id, "scan"), vm.laser_scan(m, ns), ns)


def on_virtual_scan(rec, ch, v, key: str, m: Scan, recv_ns: int) -> None:
    """A real robot's virtual returns (what the world cast against the virtual bodies), on their own channel."""
    ns = rec.stamp(m.stamp, recv_ns)
    rec.write(ch.robot[m.id]["virtual_scan"], vm.robot_topic(m.id, "virtual_scan"), vm.laser_scan(m, ns), ns)


def on_step_io(rec, ch, v, key: str, m, recv_ns: int) -> None:
    """A robot's step record (``stack.agents.steplog``): written as the agent encoded it."""
    head, payload = m
    rec.write(ch.robot[head.id][STEP_IO], vm.robot_topic(head.id, STEP_IO), payload, rec.stamp(head.t, recv_ns))


def on_state(rec, ch, v, key: str, m: State, recv_ns: int) -> None:
    ns = rec.stamp(m.stamp, recv_ns)
    rec.write(ch.tf_estimate, T["tf_estimate"], vm.estimate_transform(m, ns), ns)
    rec.write(ch.robot[m.id]["estimate"], vm.robot_topic(m.id, "estimate"), vm.pose_in_world(m.x, m.y, m.yaw, ns), ns)
    doc = {"id": m.id, "step": m.step, "role": m.role, "policy": rec.sc.robot(m.id).policy,
           "situation": m.situation or "", "x": m.x, "y": m.y, "yaw": m.yaw, "v": m.v, "w": m.w, "seq": m.seq,
           "stamp": m.stamp}  # seq and stamp: the agents' step records name the states they took by them
    doc.update({k: getattr(m, k) for k in ("cov_trace", "d_goal", "wall") if getattr(m, k) is not None})
    rec.write(ch.robot[m.id]["state"], vm.robot_topic(m.id, "state"), doc, ns)
    old = v.roles.get(m.id)
    if old is not None and old != m.role:
        rec.event(ns, f"robot {m.id}: now {m.role} (was {old}): failover", LogLevel.Warning)
    v.roles[m.id] = m.role
    v.estimates[m.id] = m


def on_cmd_vel(rec, ch, v, key: str, m: CmdVel, recv_ns: int) -> None:
    ns = rec.stamp(m.stamp, recv_ns)
    rec.write(ch.robot[m.id]["cmd_vel"], vm.robot_topic(m.id, "cmd_vel"),
              {"id": m.id, "step": m.step, "stamp": m.stamp, "v": m.v, "w": m.w}, ns)


def on_diag(rec, ch, v, key: str, m: Diag, recv_ns: int) -> None:
    ns = rec.stamp(m.stamp, recv_ns)
    doc = vm.diag_doc(m)
    rec.write(ch.robot[m.id]["diag"], vm.robot_topic(m.id, "diag"), doc, ns)
    if m.fault and v.faults.get(m.id) != m.fault:
        rec.event(ns, f"robot {m.id}: fault: {m.fault}", LogLevel.Error)
    v.faults[m.id] = m.fault
    for sender, counts in (m.links or {}).items():
        now = {k: int(counts.get(k, 0)) for k in LINK_KEYS}
        before = v.links_total.get((sender, m.id), dict.fromkeys(LINK_KEYS, 0))
        v.links_window[(sender, m.id)] = {k: max(now[k] - before[k], 0) for k in LINK_KEYS}
        v.links_total[(sender, m.id)] = now


def on_status(rec, ch, v, key: str, m: WorldStatus, recv_ns: int) -> None:
    ns = rec.stamp(m.t if m.t else v.t, recv_ns)
    rec.event(ns, f"world: {m.state}" + (f" ({m.why})" if m.why else ""))
    if m.state == "done":
        rec.done.set()


def on_fault(rec, ch, v, key: str, m: FaultRequest, recv_ns: int) -> None:
    rec.event(rec.stamp(m.t, recv_ns), f"fault: {m.kind} robots {list(m.ids)} at t={m.t:.2f} s (step {m.step})",
              LogLevel.Warning)


def on_fault_ack(rec, ch, v, key: str, m: FaultAck, recv_ns: int) -> None:
    rec.event(rec.stamp(v.t, recv_ns), f"fault carried out: {m.kind} robots {list(m.done)} (step {m.step})",
              LogLevel.Warning)


def on_alive(rec, ch, v, key: str, left: bool, recv_ns: int) -> None:
    rid = Keys.id_of(key)
    if rid is not None:
        rec.event(rec.stamp(v.t, recv_ns), f"robot {rid}: agent {'left' if left else 'up'}",
                  LogLevel.Warning if left and v.step >= 0 else LogLevel.Info)


HANDLERS = {"clock": on_clock, "truth": on_truth, "scan": on_scan, "state": on_state, "cmd_vel": on_cmd_vel,
            "diag": on_diag, "status": on_status, "fault": on_fault, "fault_ack": on_fault_ack, "alive": on_alive,
            STEP_IO: on_step_io, "virtual_scan": on_virtual_scan}
