"""Profile of one lock-step step: CPU seconds per step of each process of the fleet, and where they go.

Runs ``stack-fleet run`` in lock-step on the fleet bench's scenario (PID, 180-beam lidars, ``sim`` driver)
and reads each process's CPU time (``/proc/<pid>/stat``: user + system) at two world steps, so the numbers
are CPU seconds per step per process, robust on a machine shared with other work (wall time is reported
beside them, not relied on). With ``--py-spy`` the whole fleet runs under ``py-spy record --subprocesses``
(non-blocking, active samples only: CPU, not waits) and the samples are summed per process kind and per
phase of the step (docs/profile.md). ``--floor`` times the world's own work alone, in this process, with
per-phase CPU timers: physics, rays, encoding, Zenoh puts to a router nobody else listens on.

    python bench/profile_step.py --robots 4 32 --steps 150
    python bench/profile_step.py --robots 32 --steps 100 --py-spy runs/profile
    python bench/profile_step.py --robots 4 32 --floor
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from fleet_bench import fleet_scenario  # noqa: E402

from stack.comm import Keys, decode  # noqa: E402
from stack.comm.messages import Clock  # noqa: E402
from stack.comm.session import client, free_tcp_endpoint, open_session  # noqa: E402
from stack.fleet.procs import wait_port  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")
KINDS = (("py-spy", "py-spy"), ("stack.sim_bridge", "world"), ("stack.agents", "agent"), ("stack.comm.router", "router"), ("stack.fleet.record", "recorder"),
         ("stack-fleet", "orchestrator"), ("stack.fleet", "orchestrator"))

# the phases of a step, by the first frame (from the leaf up) that names one; py-spy frames are "func (file:line)"
PHASES = (
    ("rays (rayTestBatch)", ("_cast (",)), ("beam culling", ("_beam_mask (",)), ("ray setup", ("_rays (",)),
    ("lidar noise/ranges", ("_ranges (",)), ("physics + body sync", ("step (stack/sim_bridge/world.py", "_sync_bod")),
    ("encode (msgspec)", ("encode (",)), ("decode (msgspec)", ("decode (", "receive (")),
    ("zenoh put", ("put (",)), ("barrier / wake-ups", ("lockstep.py",)),
    ("agent step pipeline", ("step (stack/agents/step.py",)), ("state callback", ("_on_state (", "_heard_state (")),
    ("odom/imu callbacks", ("_on_odom (", "_odom_cb (", "_imu_cb (")), ("scan callback", ("_on_scan (",)),
    ("clock callback", ("_on_clock (",)), ("world truth log", ("_log_truth (",)), ("task check", ("_task_done (",)),
    ("monitor / recorder", ("monitor.py", "record.py", "viz_")),
    ("imports / startup", ("<module> (", "_find_and_load")),
)


def proc_tree(root: int) -> dict[int, str]:
    """Every descendant of ``root`` (and itself): pid -> kind."""
    children: dict[int, list[int]] = collections.defaultdict(list)
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children[ppid].append(int(d))
    out, todo = {}, [root]
    while todo:
        pid = todo.pop()
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        out[pid] = next((kind for mark, kind in KINDS if mark in cmd), "other")
        todo += children.get(pid, [])
    return out


def cpu_s(pid: int) -> float | None:
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(f[11]) + int(f[12])) / TICK  # utime + stime


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per thread name of one process (zenoh's runtime threads are named: rx-0, tx-0, app-0, ...;
    Python's own are all ``python``): the Rust side of Zenoh apart from Python's callbacks and loops."""
    out: collections.Counter = collections.Counter()
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return {}
    for tid in tids:
        try:
            text = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except OSError:
            continue
        name = text[text.index("(") + 1:text.rindex(")")].rstrip("0123456789-")
        if name in ("python", "python3", "stack-fleet"):  # Python's threads: the main one, and the callback threads
            name = "python main" if tid == str(pid) else "python other (zenoh callbacks, driver)"
        f = text.rsplit(")", 1)[1].split()
        out[name or "?"] += (int(f[11]) + int(f[12])) / TICK
    return dict(out)


class StepSampler:
    """On our own session: at world steps ``k0`` and ``k1`` the CPU seconds of every process under ``root``."""

    def __init__(self, endpoint: str, fleet: str, root: int, k0: int, k1: int):
        self.root, self.k0, self.k1 = root, k0, k1
        self.snaps: dict[int, tuple[float, dict[int, tuple[str, float]]]] = {}
        self.done = threading.Event()
        self.last = -1
        self.session = open_session(client(endpoint))
        self.sub = self.session.declare_subscriber(Keys(fleet).world("clock"), self._on_clock)

    def _on_clock(self, sample) -> None:
        k = self.last = decode(sample.payload.to_bytes(), Clock).step
        if k in (self.k0, self.k1) and k not in self.snaps:
            tree = proc_tree(self.root)
            self.snaps[k] = (time.monotonic(), {pid: (kind, thread_cpu_s(pid)) for pid, kind in tree.items()})
            if k == self.k1:
                self.done.set()

    def per_step(self) -> dict:
        (w0, a), (w1, b) = self.snaps[self.k0], self.snaps[self.k1]
        n = self.k1 - self.k0
        by_kind: dict[str, list[float]] = collections.defaultdict(list)
        threads: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        for pid, (kind, c1) in b.items():
            if pid in a:
                by_kind[kind].append(sum(c1.values()) / n - sum(a[pid][1].values()) / n)
                for name, c in c1.items():
                    threads[kind][name] += (c - a[pid][1].get(name, 0.0)) / n
        out = {"steps": n, "wall_ms_per_step": 1000 * (w1 - w0) / n, "steps_per_s": n / (w1 - w0)}
        for kind, v in sorted(by_kind.items()):
            out[kind] = {"processes": len(v), "cpu_ms_per_step_each": 1000 * sum(v) / len(v),
                         "cpu_ms_per_step_total": 1000 * sum(v),
                         "by_thread_ms_each": {t: round(1000 * c / len(v), 3) for t, c in threads[kind].most_common() if c}}
        out["cpu_ms_per_step_all"] = sum(1000 * sum(v) for v in by_kind.values())
        return out

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def run_fleet(n: int, out: Path, steps: int, skip: int, spy: Path | None, record: bool, rate: int,
              cprofile: bool = False, code: Path = ROOT) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    data = fleet_scenario(n, 900.0)  # long: the run is ended (SIGTERM) once the last step is sampled
    scen = out / f"profile-{n}.yaml"
    scen.write_text(yaml.safe_dump(data, sort_keys=False))
    ep, fleet = free_tcp_endpoint(), f"profile{os.getpid()}x{n}"
    cmd = [str(Path(sys.executable).with_name("stack-fleet")), "run", str(scen), "--out", str(out / f"run-{n}"),
           "--no-progress", "--no-plots", "--listen", ep, "--fleet", fleet, *([] if record else ["--no-record"])]
    raw = None
    if spy is not None:
        raw = spy / f"py-spy-{n}.txt"
        cmd = [str(Path(sys.executable).with_name("py-spy")), "record", "--subprocesses", "--nonblocking", "-r", str(rate),
               "-f", "raw", "-o", str(raw), "--", *cmd]
    env = dict(os.environ, PYTHONPATH=str(code))
    prof_dir = out / f"cprofile-{n}"
    if cprofile:
        prof_dir.mkdir(parents=True, exist_ok=True)
        for old in prof_dir.glob("*.prof"):
            old.unlink()
        env |= {"PYTHONPATH": f"{code}{os.pathsep}{ROOT / 'bench' / 'profile_hook'}", "STACK_CPROFILE_DIR": str(prof_dir)}
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=open(out / f"fleet-{n}.log", "wb"))
    try:
        wait_port(ep, timeout=60.0)
        sampler = StepSampler(ep, fleet, p.pid, skip, skip + steps)
        sampler.done.wait(1200.0)
        result = sampler.per_step() if sampler.done.is_set() else {"error": "the run never reached the last step"}
    finally:
        for pid, kind in proc_tree(p.pid).items():
            if kind == "orchestrator":  # it winds the fleet down (agents first) as on Ctrl-C
                os.kill(pid, signal.SIGTERM)
        p.wait(300)
    sampler.close()  # after the fleet: ``last`` is the last step the agents ran
    if raw is not None and raw.exists():
        result["py_spy"] = summarise(raw)
    if cprofile:
        steps_run = sampler.last + 1
        result["cprofile"] = {kind: summarise_cprofile(sorted(prof_dir.glob(f"{kind}-*.prof")), steps_run)
                              for kind in ("world", "agent")}
    return result


# the functions of the step whose inclusive CPU time and calls the cProfile summary reports: (label, file, function)
HOT = (
    ("world: loop (all of its main thread's step)", "server.py", "_loop"),
    ("world: publish step (clock, sensors, truth)", "server.py", "_publish_step"),
    ("world: lidar (culling, rays, noise)", "world.py", "lidar"),
    ("world: rayTestBatch", "~", "<built-in method pybullet.rayTestBatch>"),
    ("world: beam culling", "world.py", "_beam_mask"),
    ("world: physics + body sync", "world.py", "step"),
    ("world: truth log", "server.py", "_log_truth"),
    ("world: task check", "server.py", "_task_done"),
    ("world: barrier wait (wake-ups)", "lockstep.py", "wait"),
    ("world: cmd_vel callback", "server.py", "_on_cmd"),
    ("agent: loop (main thread)", "agent.py", "_loop"),
    ("agent: wait for step k (wake-ups)", "lockstep.py", "wait_step"),
    ("agent: wait for neighbours (wake-ups)", "lockstep.py", "wait_neighbours"),
    ("agent: step pipeline", "step.py", "step"),
    ("agent:   estimator", "step.py", "estimate"),
    ("agent:   neighbours + radio", "step.py", "_neighbours"),
    ("agent:   decision layer", "step.py", "_decide"),
    ("agent:   policy", "step.py", "_act"),
    ("agent: send (state, cmd_vel, diag)", "agent.py", "_send"),
    ("agent: diag", "agent.py", "_publish_diag"),
    ("agent: state callback", "agent.py", "_heard_state"),
    ("agent: scan callback", "agent.py", "_on_scan"),
    ("agent: clock callback", "agent.py", "_on_clock"),
    ("agent: odom callback", "sim.py", "_odom_cb"),
    ("agent: imu callback", "sim.py", "_imu_cb"),
    ("agent: odom to agent", "agent.py", "_on_odom"),
    ("both: msgspec decode", "messages.py", "decode"),
    ("both: msgspec encode", "messages.py", "encode"),
    ("both: zenoh put", "~", "<method 'put' of 'builtins.Publisher' objects>"),
    ("both: payload to_bytes", "~", "<method 'to_bytes' of 'builtins.ZBytes' objects>"),
    ("both: message validation (__post_init__)", "messages.py", "__post_init__"),
    ("both: notify_all", "threading.py", "notify_all"),
)


def summarise_cprofile(files: list[Path], steps: int) -> dict:
    """pstats of the processes of one kind, merged (each thread on its own CPU clock): per step and process, the
    inclusive CPU ms and the calls of the step's functions (``HOT``). cProfile's own cost inflates cheap calls:
    read the counts as exact and the times as shares."""
    import pstats

    if not files:
        return {}
    st = pstats.Stats(*map(str, files))
    per = len(files) * steps
    out = {"processes": len(files), "steps": steps}
    for label, fname, func in HOT:
        hits = [v for (fn, _, name), v in st.stats.items() if name == func and (fn == fname or fn.endswith("/" + fname))]
        if hits:
            nc, ct = sum(v[1] for v in hits), sum(v[3] for v in hits)
            out[label] = {"cum_ms": round(1000 * ct / per, 3), "calls": round(nc / per, 2)}
    return out


def floor(n: int, steps: int) -> dict:
    """The world's own work per step, alone in this process: per-phase CPU ms (thread CPU time)."""
    from stack.comm import encode
    from stack.comm.messages import Imu, Odom, Scan, Truth
    from stack.scenario import parse_scenario
    from stack.sim_bridge.world import World

    sc = parse_scenario(fleet_scenario(n, 1000.0), "profile")
    w = World(sc)
    router = subprocess.Popen([sys.executable, "-m", "stack.comm.router", "--listen", ep := free_tcp_endpoint()],
                              stdout=subprocess.DEVNULL, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        wait_port(ep, timeout=30.0)
        s = open_session(client(ep))
        keys = Keys("floor")
        pubs = {(r, t): s.declare_publisher(keys.robot(r, t)) for r in w.ids for t in ("odom", "imu", "scan")}
        t_ = collections.Counter()
        cmds = {r: (0.8, 0.05 * (r % 3 - 1)) for r in w.ids}
        lid = sc.robots[0].lidar
        for k in range(steps):
            c0 = time.thread_time()
            scans = w.lidar()
            c1 = time.thread_time()
            msgs = []
            for rid in w.ids:
                v, om, pose = w.odometry(rid, sc.dt)
                msgs.append(((rid, "odom"), encode(Odom(id=rid, step=k, stamp=0.1 * k, v=v, w=om, x=pose[0], y=pose[1], yaw=pose[2]))))
                msgs.append(((rid, "imu"), encode(Imu(id=rid, step=k, stamp=0.1 * k, wz=w.gyro(rid)))))
                msgs.append(((rid, "scan"), encode(Scan(id=rid, step=k, stamp=0.1 * k, angle_min=-lid.fov / 2,
                                                        angle_increment=lid.fov / (lid.beams - 1), range_max=lid.range,
                                                        ranges=scans[rid].tolist()))))
            encode(Truth(step=k, t=0.1 * k, ids=w.ids, x=w.x.tolist(), y=w.y.tolist(), yaw=w.yaw.tolist()))
            c2 = time.thread_time()
            for key, payload in msgs:
                pubs[key].put(payload)
            c3 = time.thread_time()
            w.step(cmds, sc.dt)
            c4 = time.thread_time()
            if k >= 10:
                t_["rays + culling"] += c1 - c0
                t_["sensors + encode"] += c2 - c1
                t_["zenoh put"] += c3 - c2
                t_["physics + body sync"] += c4 - c3
        s.close()
    finally:
        router.terminate()
        router.wait(10)
        w.close()
    m = steps - 10
    out = {ph: 1000 * v / m for ph, v in t_.items()}
    out["total"] = sum(out.values())
    out["steps_per_s_cpu"] = 1000 / out["total"]
    return out


def pipeline(n: int, steps: int) -> dict:
    """One follower's control step (``StepPipeline.step``) alone, fed what the world would send it: CPU ms per
    step of its parts (thread CPU time, no profiler), with n - 1 neighbours' states a step."""
    from stack.comm.messages import Scan, State
    from stack.agents.step import OdomSample, StepInputs, StepPipeline
    from stack.scenario import parse_scenario
    from stack.sim_bridge.world import World

    sc = parse_scenario(fleet_scenario(n, 1000.0), "profile")
    w, me = World(sc), 1
    pl = StepPipeline(sc, me)
    lid = sc.robots[me].lidar
    parts = collections.Counter()
    timed = {name: getattr(pl, name) for name in ("estimate", "_neighbours", "_decide", "_act")}
    for name, fn in timed.items():
        def wrap(*args, _fn=fn, _name=name):
            c = time.thread_time()
            try:
                return _fn(*args)
            finally:
                parts[_name] += time.thread_time() - c
        setattr(pl, name, wrap)
    total = 0.0
    for k in range(steps):
        t = 0.1 * k
        scans = w.lidar()
        v, om, pose = w.odometry(me, 0.1)
        states = tuple(State(id=r, role="follower" if r else "leader", seq=k, stamp=t - 0.1, x=float(w.x[i]),
                             y=float(w.y[i]), yaw=float(w.yaw[i]), v=float(w.v[i]), w=float(w.w[i]), step=k - 1)
                       for i, r in enumerate(w.ids) if r != me) if k else ()
        inp = StepInputs(step=k, t=t, t_run=t, now=t, odometry=(OdomSample(v, om, t, w.gyro(me), pose),),
                         scan=Scan(id=me, step=k, stamp=t, angle_min=-lid.fov / 2, angle_increment=lid.fov / (lid.beams - 1),
                                   range_max=lid.range, ranges=scans[me].tolist()), scan_t=t, states=states)
        if k == 10:
            parts.clear()
            total = 0.0
        c = time.thread_time()
        out = pl.step(inp)
        total += time.thread_time() - c
        w.step({r: (0.8, 0.0) for r in w.ids if r != me} | {me: (out.v, out.w)}, 0.1)
    w.close()
    m = steps - 10
    return {"step_ms": 1000 * total / m, **{f"{k}_ms": 1000 * v / m for k, v in parts.items()}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[4, 32])
    ap.add_argument("--steps", type=int, default=150, help="steps measured")
    ap.add_argument("--skip", type=int, default=30, help="steps before the measurement starts")
    ap.add_argument("--py-spy", type=Path, metavar="DIR", help="record the fleet with py-spy; raw stacks into DIR")
    ap.add_argument("--rate", type=int, default=50, help="py-spy samples per second")
    ap.add_argument("--record", action="store_true", help="keep the fleet's MCAP recording on (as the fleet bench runs)")
    ap.add_argument("--cprofile", action="store_true", help="cProfile every thread of the world and the agents")
    ap.add_argument("--pipeline", action="store_true", help="one agent's step pipeline alone, in this process")
    ap.add_argument("--floor", action="store_true", help="the world's own work alone, in this process")
    ap.add_argument("--code", type=Path, default=ROOT, help="run the fleet of this checkout (e.g. a baseline worktree)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "profile")
    a = ap.parse_args(argv)
    if a.py_spy is not None:
        a.py_spy.mkdir(parents=True, exist_ok=True)
    results = {}
    for n in a.robots:
        res = floor(n, a.steps) if a.floor else pipeline(n, a.steps) if a.pipeline else run_fleet(n, a.out, a.steps, a.skip, a.py_spy, a.record, a.rate, a.cprofile, a.code)
        results[n] = res
        print(json.dumps({"robots": n, **res}, indent=1), flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / ("floor.json" if a.floor else "pipeline.json" if a.pipeline else "profile.json")).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
