"""``stack-fleet run|bench``: argument parsing only; the work is in :mod:`.orchestrator` and :mod:`.bench`."""

from __future__ import annotations

import argparse
import logging
import os
import re
import sys
from pathlib import Path

from ..argtypes import fleet_name, nonnegative_float, nonnegative_int, positive_int
from ..comm.session import ConfigFileError, EndpointError, SessionConfig, SessionError, check_endpoint, endpoint_list, port_free, zenoh_config
from ..policies import available as available_policies
from ..scenario import FAULT_KINDS, ScenarioError, driver_names, load_scenario, parse_fault_at, policy_names, with_overrides
from .orchestrator import EXIT_BAD_INPUT, FleetConfig, run_fleet, sigterm_as_interrupt


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        print(f"{self.prog}: {message}", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)


def _fault_at(text: str) -> tuple[int, float]:
    try:
        return parse_fault_at(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _sweep(text: str):
    from .bench import parse_sweep

    try:
        return parse_sweep(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _prob(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a probability in [0, 1], got {text!r}") from None
    if not 0.0 <= x <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a probability in [0, 1], got {text!r}")
    return x


def _positive(text: str) -> float:
    x = nonnegative_float(text)
    if x == 0:
        raise argparse.ArgumentTypeError("expected a number > 0, got 0")
    return x


def parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="stack-fleet", description="Run and benchmark simulated formations.")
    sub = ap.add_subparsers(dest="cmd", required=True, parser_class=_Parser)
    r = sub.add_parser("run", help="run one scenario: router, world, one agent per robot; writes report.json and plots")
    r.add_argument("scenario", help="scenario YAML")
    r.add_argument("--out", type=Path, help="output folder (default runs/<scenario>)")
    r.add_argument("--policy", choices=policy_names(), help="override every robot's policy")
    r.add_argument("--driver", choices=driver_names(), help="override every robot's driver")
    r.add_argument("--loss", type=_prob, help="override comm.loss")
    r.add_argument("--latency-ms", type=nonnegative_float, help="override comm.latency_ms")
    r.add_argument("--seed", type=int, help="override the seed of every random source")
    r.add_argument("--duration", type=_positive, help="override the duration [s]")
    r.add_argument("--realtime", action="store_true", help="run on the wall clock (default: lock-step, as fast as agents answer)")
    r.add_argument("--gui", action="store_true", help="pybullet GUI")
    r.add_argument("--listen", help="router endpoint, e.g. tcp/127.0.0.1:7447 (default: a free loopback port)")
    r.add_argument("--kill", type=_fault_at, action="append", default=[], metavar="ID@T", help="SIGKILL robot ID's agent at sim time T")
    r.add_argument("--freeze", type=_fault_at, action="append", default=[], metavar="ID@T",
                   help="SIGSTOP robot ID's agent at sim time T (a hung process: its driver watchdog stops the robot)")
    r.add_argument("--restart", type=_fault_at, action="append", default=[], metavar="ID@T",
                   help="start robot ID's agent again at sim time T (after a --kill or --freeze: it rejoins)")
    r.add_argument("--can-log", action="store_true", help="log every CAN robot's bus to DIR/logs/can-<id>.asc (can.Logger)")
    r.add_argument("--device-fault", type=_fault_at, action="append", default=[], metavar="ID@T",
                   help="robot ID's simulated device fails at sim time T (CAN: heartbeats stop; MAVLink: HOLD; Jackal: odometry stops)")
    r.add_argument("--connect", metavar="EP", help="join this (site) router instead of starting one; several, comma-separated: any of them")
    r.add_argument("--external-agents", action="store_true",
                   help="start no agents: they run elsewhere (stack-agent on each robot); wait for their tokens")
    r.add_argument("--wait-agents", type=float, default=60.0, metavar="S", help="how long to wait for every agent (default 60 s)")
    r.add_argument("--rejoin-wait", type=float, default=10.0, metavar="S",
                   help="real time: how long a robot out of contact (its network, or the world's) may take to come back "
                        "before it is gone (default 10 s)")
    r.add_argument("--lockstep-timeout", type=float, default=2.0, metavar="S",
                   help="lock-step: how long (wall) the world waits for an agent's command before it goes on without it "
                        "(a late step) and stops waiting for that agent (default 2 s)")
    r.add_argument("--fleet", type=fleet_name, help="fleet name, the key prefix stack/<fleet>/ (default: one per run)")
    r.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config (deploy/: TLS, access control) for the fleet's sessions")
    r.add_argument("--allow-remote", action="store_true", help="allow router endpoints off loopback (multi-host)")
    r.add_argument("--no-progress", action="store_true", help="no live progress line")
    r.add_argument("--no-plots", action="store_true", help="skip trajectories.png, distances.png and replay.gif")
    r.add_argument("--no-record", action="store_true", help="do not write run.mcap (nor replay.gif)")
    r.add_argument("--viz", nargs="?", const="tcp/127.0.0.1:8765", metavar="EP",
                   help="serve the run live to Foxglove / Lichtblick (ws) on EP (default tcp/127.0.0.1:8765; "
                        "off loopback only with --allow-remote)")
    r.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    sub.add_parser("generate", add_help=False, help="write a generated, solvable obstacle course (docs/courses.md)")
    p = sub.add_parser("replay", help="animate a run from its run.mcap (replay.gif), without any app; --verify: "
                                      "replay every robot's steps to the bit")
    p.add_argument("run_dir", type=Path, help="a run's folder (or its run.mcap)")
    p.add_argument("--verify", action="store_true", help="replay every robot's recorded steps through its pipeline "
                   "(stack-replay); exit 1 naming any robot that does not reproduce to the bit")
    p.add_argument("--out", default="replay.gif", help="GIF to write, relative to RUN_DIR (default replay.gif)")
    p.add_argument("--max-frames", type=positive_int, default=150)
    p.add_argument("--fps", type=_positive, default=10.0)
    p.add_argument("--width", type=positive_int, default=640, help="pixels (height: 3/4 of it)")
    b = sub.add_parser("bench", help="every scenario x every fitting policy; one table (markdown + JSON)")
    b.add_argument("--out", type=Path, default=Path("runs/bench"))
    b.add_argument("--scenarios", type=Path, default=Path("scenarios"), help="folder of scenario files")
    b.add_argument("--seed", type=int, help="override every scenario's seed")
    b.add_argument("--sweep", type=_sweep, metavar="PARAM=V1,V2,...",
                   help="sweep loss, latency_ms or burst (Gilbert-Elliott with that mean loss) over values x --seeds")
    b.add_argument("--seeds", type=positive_int, default=3, help="seeds per sweep value (0..N-1)")
    b.add_argument("--policies", type=lambda t: t.split(","), help="comma-separated policies (default: each scenario's)")
    b.add_argument("--duration", type=float, help="override every scenario's duration [s]")
    b.add_argument("--random", type=positive_int, metavar="N", help="bench N generated courses instead (docs/courses.md)")
    b.add_argument("--first-seed", type=nonnegative_int, default=0, help="--random: the first course seed (default 0)")
    b.add_argument("--robots", type=positive_int, help="--random: robots per course (default: drawn, 3..8)")
    b.add_argument("--formation", help="--random: formation family (default: drawn)")
    b.add_argument("--density", help="--random: obstacle density low|medium|high (default: drawn)")
    from .jobs import add_engine_args

    add_engine_args(b)
    return ap


def _faults(a: argparse.Namespace, sc) -> list[tuple[str, int, float]]:
    """``--kill/--freeze/--restart`` as (kind, id, t), and ``--device-fault`` checked: robots that exist, times in the run."""
    ids = set(sc.ids)
    faults = []
    for kind in FAULT_KINDS:
        for rid, t in getattr(a, kind):
            if rid not in ids:
                raise ScenarioError(f"--{kind} {rid}@{t:g}: no robot with id {rid} in {a.scenario}")
            if t > sc.duration:
                raise ScenarioError(f"--{kind} {rid}@{t:g}: after the run's end ({sc.duration:g} s)")
            faults.append((kind, rid, t))
    from ..sim_bridge.devices import hosted

    with_device = [r.id for r in sc.robots if r.driver in hosted()]
    for rid, t in a.device_fault:
        if rid not in with_device:
            raise ScenarioError(f"--device-fault {rid}@{t:g}: robot {rid} has no simulated device "
                                f"(robots with one: {', '.join(map(str, with_device)) or 'none'})")
        if t > sc.duration:
            raise ScenarioError(f"--device-fault {rid}@{t:g}: after the run's end ({sc.duration:g} s)")
    return faults


def run_config(a: argparse.Namespace) -> FleetConfig:
    sc = load_scenario(a.scenario)
    sc = with_overrides(sc, policy=a.policy, driver=a.driver, loss=a.loss, latency_ms=a.latency_ms, seed=a.seed,
                        duration=a.duration)
    missing = sorted({r.policy for r in sc.robots} - set(available_policies()))
    if missing:
        raise ScenarioError(f"{a.scenario}: policy {', '.join(missing)} is not implemented yet (available: {', '.join(available_policies())})")
    from ..sim_bridge.devices import hosted

    hostable = sorted(set(hosted()) | {"sim"})
    drivers = sorted({r.driver for r in sc.robots} - set(hostable))
    if drivers:
        raise ScenarioError(f"{a.scenario}: driver {', '.join(drivers)} is not implemented yet (available: {', '.join(hostable)})")
    faults = _faults(a, sc)
    if a.listen:
        check_endpoint(a.listen)
        if not re.fullmatch(r"tcp/[^#?]+:\d+", a.listen):
            raise ScenarioError(f"--listen {a.listen}: the fleet's router listens on TCP (tcp/HOST:PORT)")
        if not port_free(a.listen):
            raise ScenarioError(f"--listen {a.listen}: address in use")
    if a.connect:
        if a.listen:
            raise ScenarioError("--connect and --listen: give one (join a router, or start ours on an endpoint)")
        endpoint_list(a.connect, a.allow_remote)
    real = [r.id for r in sc.robots if r.embodiment == "real"]
    if real and not a.realtime:
        raise ScenarioError(f"{a.scenario}: robots {real} are real (embodiment: real): a fleet with real robots runs in "
                            f"real time (--realtime)")
    for kind, rid, _ in faults:
        if rid in real:
            raise ScenarioError(f"--{kind} {rid}@...: robot {rid} is real; its agent runs where the robot is, not here")
    for rid, _ in a.device_fault:
        if rid in real:
            raise ScenarioError(f"--device-fault {rid}@...: robot {rid} is real; the world hosts no device for it")
    if a.external_agents and faults:
        raise ScenarioError("--external-agents: faults (--kill/--freeze/--restart) need agents this command started")
    if a.wait_agents <= 0:
        raise ScenarioError(f"--wait-agents: must be > 0, got {a.wait_agents:g}")
    if a.rejoin_wait < 0:
        raise ScenarioError(f"--rejoin-wait: must be >= 0, got {a.rejoin_wait:g}")
    if not a.lockstep_timeout > 0:
        raise ScenarioError(f"--lockstep-timeout: must be > 0, got {a.lockstep_timeout:g}")
    if a.zenoh_config is not None and not Path(a.zenoh_config).is_file():
        raise ScenarioError(f"--zenoh-config {a.zenoh_config}: no such file")
    if a.zenoh_config is not None:
        try:  # read it here, so a broken file is bad input (exit 2), not a crash of every process
            zenoh_config(SessionConfig(config_file=a.zenoh_config, allow_remote=True))
        except ConfigFileError as e:
            raise ScenarioError(f"--zenoh-config {e}") from None
    if a.gui and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ScenarioError("--gui: no display (DISPLAY is not set); run without --gui, or under a desktop or Xvfb")
    if a.viz is not None:
        from .record import parse_viz_endpoint

        try:
            parse_viz_endpoint(a.viz, a.allow_remote)
        except ValueError as e:
            raise ScenarioError(str(e)) from None
    out = a.out or Path("runs") / sc.name
    if out.exists() and not out.is_dir():
        raise ScenarioError(f"--out {out}: exists and is not a folder")
    return FleetConfig(scenario=sc, out=out, realtime=a.realtime, gui=a.gui, listen=a.listen, faults=faults,
                       device_faults=a.device_fault, can_log=a.can_log,
                       progress=not a.no_progress, plots=not a.no_plots, connect=a.connect,
                       external_agents=a.external_agents, wait_agents_s=a.wait_agents, rejoin_wait_s=a.rejoin_wait,
                       lockstep_timeout_s=a.lockstep_timeout, fleet=a.fleet,
                       zenoh_config=a.zenoh_config, allow_remote=a.allow_remote, record=not a.no_record, viz=a.viz)


def cli(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["generate"]:
        from .courses import main as generate_main

        return generate_main(argv[1:], prog="stack-fleet generate")
    a = parser().parse_args(argv)
    if a.cmd == "replay" and a.verify:
        from ..replay.cli import verify

        return verify(a.run_dir)
    if a.cmd == "replay":
        from .replay import main as replay_main

        return replay_main([str(a.run_dir), "--out", a.out, "--max-frames", str(a.max_frames), "--fps", str(a.fps),
                            "--width", str(a.width)])
    if a.cmd == "bench":
        from .bench import main as bench_main
        from .jobs import EngineError, engine_config

        try:
            engine = engine_config(a)
        except EngineError as e:
            print(f"stack-fleet: {e}", file=sys.stderr)
            return EXIT_BAD_INPUT
        sigterm_as_interrupt()
        try:
            if a.random is not None:
                from .bench import random_bench

                return random_bench(a.random, a.out, first_seed=a.first_seed, robots=a.robots, formation=a.formation,
                                    density=a.density, policies=a.policies, seed=a.seed, engine=engine)
            if a.sweep is not None:
                from .bench import sweep

                bad = [p for p in (a.policies or []) if p not in policy_names()]
                if bad:
                    print(f"stack-fleet: --policies: unknown policy {bad[0]!r} (one of {', '.join(policy_names())})",
                          file=sys.stderr)
                    return EXIT_BAD_INPUT
                return sweep(a.scenarios, a.out, a.sweep[0], a.sweep[1], seeds=a.seeds, policies=a.policies,
                             duration=a.duration, engine=engine)
            return bench_main(a.scenarios, a.out, seed=a.seed, engine=engine)
        except KeyboardInterrupt:
            print("stack-fleet: interrupted; every process was stopped", file=sys.stderr)
            return 130
    logging.basicConfig(level=a.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        cfg = run_config(a)
    except (ScenarioError, EndpointError) as e:
        print(f"stack-fleet: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    sigterm_as_interrupt()
    try:
        code, report = run_fleet(cfg)
    except SessionError as e:
        print(f"stack-fleet: {e}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("stack-fleet: interrupted; every process was stopped", file=sys.stderr)
        return 130
    _summary(report, cfg.out, code)
    return code


def _summary(rep: dict, out: Path, code: int) -> None:
    verdict = {0: "SUCCESS", 1: "FAILED", 3: "CRASHED"}.get(code, str(code))
    print(f"{verdict}: {rep['scenario']} (seed {rep['seed']}) sim {rep['sim_time_s']} s in {rep['wall_time_s']} s wall; "
          f"leader at goal {rep['leader_time_to_goal_s']} s; collisions {rep['collisions']}; "
          f"min/max robot distance {rep['min_robot_distance_m']}/{rep['max_robot_distance_m']} m; "
          f"formation error rms {rep['formation_error_rms_m']} m")
    for c in rep.get("crashed", []):
        print(f"  crashed: {c['process']} (exit {c['exit_code']}): {c['log_tail']}")
    print(f"report: {out / 'report.json'}")
    if (out / "trajectories.png").exists():
        print(f"plots:  {out / 'trajectories.png'}, {out / 'distances.png'}")
    if (out / "run.mcap").exists():
        print(f"recording: {out / 'run.mcap'} (Foxglove / Lichtblick: docs/visualisation.md)"
              + (f"; replay: {out / 'replay.gif'}" if (out / "replay.gif").exists() else ""))


def main() -> None:
    try:
        code = cli()
    except BrokenPipeError:  # stdout closed early (``| head``): the run itself ended as it should
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = 1
    sys.exit(code)


if __name__ == "__main__":
    main()
