"""``python -m stack.sim_bridge``: the world process (started by ``stack-fleet run``)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from ..comm.session import ConfigFileError, EndpointError, SessionConfig, SessionError, endpoint_list, open_session
from ..scenario import FAULT_KINDS, ScenarioError, load_scenario, parse_fault_at
from .devices import DeviceError
from .server import WorldConfig, WorldServer

log = logging.getLogger("stack.world")


def main(cfg: WorldConfig) -> int:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: cfg.stop.set())
    with open_session(SessionConfig(mode="client", connect=cfg.connect.split(","), config_file=cfg.zenoh_config,
                                    allow_remote=cfg.allow_remote)) as session:
        server = WorldServer(cfg, session)
        try:
            result = server.run()
        except KeyboardInterrupt:
            return 0
    server.write_result(result)
    print(f"world: {result['end_reason']} at t={result['sim_time_s']:.1f} s after {result['steps']} steps", flush=True)
    return 0


def cli(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="stack-world", description="The pybullet world of a simulated fleet, on Zenoh.")
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="router endpoint(s), comma-separated")
    ap.add_argument("--fleet", default="default")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--realtime", action="store_true")
    ap.add_argument("--gui", action="store_true")
    ap.add_argument("--duration", type=float)
    ap.add_argument("--wait-agents", type=float, default=60.0)
    ap.add_argument("--rejoin-wait", type=float, default=10.0, metavar="S",
                    help="real time: how long a robot out of contact may take to come back before it is gone")
    ap.add_argument("--lockstep-timeout", type=float, default=2.0)
    ap.add_argument("--linger", type=float, default=10.0, metavar="S",
                    help="after the run, how long to wait for the agents to leave (default 10 s)")
    ap.add_argument("--no-stop-early", action="store_true", help="run the whole duration even when the task is done")
    ap.add_argument("--no-agents", action="store_true",
                    help="host the robots and their devices without agents of this fleet: wait for none (with "
                         "--realtime: a stand-in for the real site of a fleet with real robots)")
    ap.add_argument("--mocap", type=_mocap, action="append", default=[], metavar="ID:KEY[:RATE_HZ[:LATENCY_MS]]",
                    help="a simulated motion-capture system: robot ID's pose as geometry_msgs/PoseStamped on KEY "
                         "(default 100 Hz, 0 ms; real time)")
    ap.add_argument("--log-level", default="WARNING")
    ap.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config layered under ours (deploy/)")
    ap.add_argument("--allow-remote", action="store_true", help="allow a router endpoint off loopback")
    ap.add_argument("--device-fault", type=_fault_at, action="append", default=[], metavar="ID@T",
                    help="robot ID's simulated device fails at sim time T")
    for kind in FAULT_KINDS:
        ap.add_argument(f"--{kind}", type=_fault_at, action="append", default=[], metavar="ID@T",
                        help=f"ask for a {kind} of robot ID's agent at sim time T (on world/fault)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=a.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        sc = load_scenario(a.scenario)
        endpoint_list(a.connect, a.allow_remote)
        for m in a.mocap:
            if m.robot not in sc.ids:
                raise ScenarioError(f"--mocap: no robot {m.robot} in the scenario")
        if (a.mocap or a.no_agents) and not a.realtime:
            raise ScenarioError("--mocap and --no-agents run on the wall clock: add --realtime")
        for flag, v in (("--rejoin-wait", a.rejoin_wait), ("--linger", a.linger)):
            if not v >= 0:
                raise ScenarioError(f"{flag}: must be >= 0, got {v:g}")
        real = [r.id for r in sc.robots if r.embodiment == "real"]
        if real and not a.realtime:
            raise ScenarioError(f"robots {real} are real (embodiment: real): a fleet with real robots runs in real "
                                f"time (--realtime); lock-step cannot wait for a real robot's step")
    except (ScenarioError, EndpointError) as e:
        print(f"stack-world: {e}", file=sys.stderr)
        return 2
    cfg = WorldConfig(scenario=sc, connect=a.connect, fleet=a.fleet, out=a.out, realtime=a.realtime, gui=a.gui,
                      wait_agents_s=a.wait_agents, rejoin_wait_s=a.rejoin_wait, lockstep_timeout_s=a.lockstep_timeout, linger_s=a.linger, duration=a.duration,
                      stop_early=not a.no_stop_early, no_agents=a.no_agents, mocap=a.mocap, zenoh_config=a.zenoh_config, allow_remote=a.allow_remote,
                      device_faults=a.device_fault, faults=[(kind, rid, t) for kind in FAULT_KINDS for rid, t in getattr(a, kind)])
    try:
        return main(cfg)
    except (ConfigFileError, DeviceError, SessionError, TimeoutError) as e:
        # one line; bad input (a config file, a device the world cannot host) is 2, the rest 1
        print(f"world: {e}", file=sys.stderr)
        return 2 if isinstance(e, (ConfigFileError, DeviceError)) else 1


def _mocap(text: str):
    from .mocap_sim import parse_mocap

    try:
        return parse_mocap(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _fault_at(text: str) -> tuple[int, float]:
    try:
        return parse_fault_at(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
