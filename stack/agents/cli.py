"""``stack-agent``: one robot's process. Argument parsing here; the work is in :func:`main`."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

from ..argtypes import fleet_name
from ..comm.session import ConfigFileError, EndpointError, SessionConfig, SessionError, endpoint_list, open_session
from ..drivers import DriverError, UnknownDriver
from ..policies import PolicyUnavailable
from ..policies import factory as policy_factory
from ..robotfile import describe, load_mission
from ..scenario import ScenarioError, driver_names, policy_names, with_driver_settings, with_overrides
from ..viz import RecorderError, VizUnavailable, require_sdk
from ..viz.endpoint import DEFAULT_VIZ, parse_viz_endpoint
from .agent import Agent, AgentConfig
from .check import CHECK_DURATION_S, run_check

log = logging.getLogger("stack.agent")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        print(f"{self.prog}: {message}", file=sys.stderr)
        sys.exit(2)


def parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="stack-agent", description="One robot of a formation: sensors, estimator, decision layer, policy, driver.")
    ap.add_argument("--id", type=int, required=True, help="robot id in the scenario")
    ap.add_argument("--role", choices=("leader", "follower", "peer"), help="must match the scenario (checked)")
    ap.add_argument("--scenario", required=True, help="scenario YAML")
    ap.add_argument("--policy", choices=policy_names(), help="override the robot's policy")
    ap.add_argument("--driver", choices=driver_names(), help="override the robot's driver")
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="Zenoh router endpoint(s), comma-separated: the robot joins the first it reaches and, having lost it, any of them (default %(default)s)")
    ap.add_argument("--fleet", default="default", type=fleet_name, help="fleet name, the key prefix stack/<fleet>/ (default %(default)s)")
    ap.add_argument("--lockstep", action="store_true", help="answer the simulated world's steps (set by stack-fleet)")
    ap.add_argument("--steps", type=int, help="stop after this many control steps")
    ap.add_argument("--seed", type=int, help="seed of every random source (default: the scenario's)")
    ap.add_argument("--allow-remote", action="store_true", help="allow a router endpoint off loopback")
    ap.add_argument("--can-log", metavar="FILE", help="can driver: log every frame to FILE (.asc, .blf, .log, .csv; can.Logger)")
    ap.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config layered under ours (deploy/: TLS, access control)")
    ap.add_argument("--robot", metavar="FILE", help="this robot's own settings, layered over its entry in --scenario")
    ap.add_argument("--check", action="store_true", help="open the robot's devices, report what is there, command nothing")
    ap.add_argument("--check-duration", type=float, default=CHECK_DURATION_S, metavar="S",
                    help="--check: how long to listen (default %(default)s s)")
    ap.add_argument("--record", metavar="FILE", help="record this robot's own view to an MCAP file (the 'viz' extra)")
    ap.add_argument("--viz", nargs="?", const=DEFAULT_VIZ, metavar="EP",
                    help=f"serve this robot's own view live, Foxglove WebSocket (default {DEFAULT_VIZ}; loopback unless --allow-remote)")
    ap.add_argument("--log-steps", action="store_true",
                    help="publish every control step's inputs and outputs (step_io) for a recorder elsewhere")
    ap.add_argument("--step-log", metavar="FILE",
                    help="append every control step's inputs and outputs to FILE, a JSON line a step (set by a recording stack-fleet)")
    ap.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return ap


def config_from_args(a: argparse.Namespace) -> AgentConfig:
    sc = load_mission(a.scenario, a.id, a.robot)
    robot = sc.robot(a.id)
    role = robot.role or "peer"
    if a.role is not None and a.role != role:
        raise ScenarioError(f"--role: robot {a.id} is {role} in {a.scenario}, not {a.role}")
    if a.steps is not None and a.steps < 1:
        raise ScenarioError(f"--steps: must be >= 1, got {a.steps}")
    endpoint_list(a.connect, a.allow_remote)
    _check_flags(a)
    if a.policy or a.driver:
        sc = with_overrides(sc, policy=a.policy, driver=a.driver)
    if a.can_log:
        driver = sc.robot(a.id).driver
        if driver != "can":
            raise ScenarioError(f"--can-log: robot {a.id}'s driver is {driver}, not can")
        sc = with_driver_settings(sc, {a.id: {"can_log": a.can_log}})
    log.info("agent %d resolved (%s%s): %s", a.id, a.scenario, f" + {a.robot}" if a.robot else "",
             describe(sc.robot(a.id)))
    if a.viz is not None:
        parse_viz_endpoint(a.viz, a.allow_remote)
    if a.record or a.viz is not None:
        require_sdk("--record" if a.record else "--viz")
    if a.step_log:
        try:
            open(a.step_log, "ab").close()  # noqa: SIM115 - only whether it can be written, before any command
        except OSError as e:
            raise ScenarioError(f"--step-log {a.step_log}: cannot write ({e.strerror or e})") from None
    return AgentConfig(robot_id=a.id, scenario=sc, connect=a.connect, fleet=a.fleet, lockstep=a.lockstep,
                       steps=a.steps, seed=a.seed, zenoh_config=a.zenoh_config, allow_remote=a.allow_remote,
                       record=a.record, viz=a.viz, log_steps=a.log_steps,
                       step_log=a.step_log)


def _check_flags(a: argparse.Namespace) -> None:
    if a.check and a.lockstep:
        raise ScenarioError("--check: listens in real time, not with --lockstep")
    if not 0.0 < a.check_duration <= 600.0:
        raise ScenarioError(f"--check-duration: must be in (0, 600] s, got {a.check_duration:g}")


STOP_GRACE_S = 3.0
"""After SIGINT/SIGTERM, how long a control step may still run (a planner mid-plan) before the robot is
commanded zero from beside it and the process ends (the fleet's own grace is 5-10 s, then SIGKILL)."""


def stop_deadline(agent_of, done: threading.Event, grace: float = STOP_GRACE_S, exit_=os._exit) -> None:
    """Wait ``grace`` s for the agent to return (``done``); if its step is still busy, zero velocity on its
    driver (thread-safe: the driver base locks each command) and end the process at once (code 0: it was
    asked to stop, and did, with its zero command)."""
    if done.wait(grace):
        return
    agent = agent_of()
    log.warning("agent %s: still in a control step %.0f s after the stop signal: zero velocity, exit",
                getattr(agent, "id", "?"), grace)
    if agent is not None:
        agent.driver.stop()
    for h in logging.getLogger().handlers:
        h.flush()
    exit_(0)


class StopDeadline:
    """:func:`stop_deadline` in its own thread, started once (:meth:`arm`, from a signal handler)."""

    def __init__(self, agent_of, done: threading.Event, grace: float = STOP_GRACE_S, exit_=os._exit):
        self.args = (agent_of, done, grace, exit_)
        self.thread: threading.Thread | None = None

    def arm(self) -> None:
        if self.thread is None:
            self.thread = threading.Thread(target=stop_deadline, args=self.args, name="stop-deadline", daemon=True)
            self.thread.start()


def main(cfg: AgentConfig) -> int:
    """Run one agent until its stop event, ``steps``, or a signal; zero velocity on every way out."""
    holder: list[Agent] = []
    done = threading.Event()
    deadline = StopDeadline(lambda: holder[0] if holder else None, done)

    def on_signal(signum, _frame):
        log.info("agent %d: %s: stopping", cfg.robot_id, signal.Signals(signum).name)
        deadline.arm()  # from the first signal, whether or not the agent was stopping already (world done)
        cfg.stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    log.info("agent %d config: %s", cfg.robot_id, {k: v for k, v in vars(cfg).items() if k not in ("scenario", "stop")})
    try:
        with open_session(SessionConfig(mode="client", connect=cfg.connect.split(","), config_file=cfg.zenoh_config,
                                        allow_remote=cfg.allow_remote)) as session:
            agent = Agent(cfg, session)
            holder.append(agent)
            return agent.run()
    finally:
        done.set()
        # The robot has its zero command; from here on a SIGINT/SIGTERM (the fleet stopping an agent that is
        # already on its way out, e.g. after the world said "done") must not kill the interpreter's
        # finalisation: Python restores SIG_DFL there for Python-level handlers, but keeps SIG_IGN.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)


def cli(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    logging.basicConfig(level=a.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        cfg = config_from_args(a)
    except (ScenarioError, EndpointError, ValueError, VizUnavailable) as e:  # ValueError: a bad --viz endpoint
        print(f"stack-agent: {e}", file=sys.stderr)
        return 2
    try:
        policy_factory(cfg.policy or cfg.scenario.robot(cfg.robot_id).policy)  # a missing extra: said before connecting
        return run_check(cfg, a.check_duration) if a.check else main(cfg)
    except (PolicyUnavailable, UnknownDriver, ConfigFileError, RecorderError) as e:
        print(f"stack-agent: {e}", file=sys.stderr)
        return 2
    except (TimeoutError, SessionError, DriverError) as e:  # e.g. a device that does not answer: zero was sent
        print(f"stack-agent: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(cli())
